"""Hypotheses over a drive: the places a search found, followed scan by scan and judged on the
same frames of the drive.

A corridor's repeating doors or a room's twin can match a scan as well as the true place;
the drive tells them apart. With odometry a hypothesis' pose implies where the robot stood on
every earlier keyframe: all are judged on the same keyframes, back-scored on those before a
search found them (docs/decisions/0017). Work is in reference ms (:data:`.global_search.
WORK_MS`): the same scans give the same poses on any machine.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.core.pose import compose, relative
from service.core.reloc import global_search as gs
from service.core.reloc.composite import composite_scan
from service.core.reloc.config import GlobalConfig
from service.core.reloc.view_index import ViewIndex
from service.core.sensor.scoring import EFFECTIVE_BEAMS, beam_fractions, subsample
from service.core.shapes.configuration import Configuration
from service.core.tracking.shape_config import ShapeConfig
from service.core.types import wrap_angle

#: Turn (rad) between two scans without odometry (the tracker's max_turn), for ``merge``.
TURN_BETWEEN_SCANS = 1.3
#: Polish stages (step m, step rad) of a track's first keyframe: +-0.43 m / +-10 degrees.
WIDE_POLISH = ((0.15, 0.06), (0.05, 0.02), (0.015, 0.006))
#: A keyframe every this far (m; closer scans repeat its evidence) or this turn (rad).
EVIDENCE_SPACING = 0.3
EVIDENCE_TURN = 0.3
#: At most this many keyframes in the window (``GlobalConfig.evidence_span``).
EVIDENCE_FRAMES = 20
#: Without odometry the window holds the last this many scans.
SCAN_WINDOW = 6
#: A frame's cost is clipped here: one keyframe with a person in view must not outweigh a drive.
EVIDENCE_CLIP = 1.0
#: A track this many nats below the leader or the unseen place on 3+ frames is let go.
EVIDENCE_DROP = 60.0
#: Weight of the moved pose as the re-scoring polish's prior: without it tracks slide in corridors.
RESCORE_PRIOR = 0.02
#: Mean predicted range (m) beyond which the unseen place's cost rises (GlobalConfig.null_slope).
NULL_REACH = 5.0
#: With odometry the search matches the last this many scans fused into this many beams,
#: leaving out scans farther than this (m) from the newest (their occlusions no longer hold).
COMPOSITE_SCANS = 3
COMPOSITE_BINS = 720
COMPOSITE_TRAVEL = 0.5


@dataclass(eq=False)
class Frame:
    """A scan of the drive's evidence: ``key`` its serial number, the judged beams (valid
    returns), robot-frame ``points`` for the polish, its ``odom`` pose (``None`` without
    odometry) and the drive's ``travel`` there (m)."""

    key: int
    ranges: np.ndarray
    angles: np.ndarray
    points: np.ndarray
    odom: np.ndarray | None
    travel: float


@dataclass(eq=False)
class Track:
    """A hypothesis followed over the drive: ``pose`` now, ``hyp`` its latest verification,
    per frame key its log-likelihood ``ll`` (nats), pose ``at`` and the unseen place's cost
    ``null`` there; ``found`` by how many searches; ``checked``: its twin check ran."""

    pose: np.ndarray
    hyp: gs.Hypothesis
    ll: dict[int, float] = field(default_factory=dict)
    at: dict[int, np.ndarray] = field(default_factory=dict)
    found: int = 1
    checked: bool = False
    null: dict[int, float] = field(default_factory=dict)

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update({"null": {}, **state})  # pickled before it had ``null``

    def record(self, key: int, cost: float, pose: np.ndarray) -> None:
        """Its evidence on frame ``key``: the beam cost ``cost`` at ``pose``."""
        self.ll[key] = loglik(cost)
        self.at[key] = pose.copy()


@dataclass(eq=False)
class Job:
    """A search in progress: its steps, the odometry pose of its scan, the ``track`` a twin
    check is for, or without odometry the plain-scan ``frame`` it searched."""

    steps: Generator[float, None, Any]
    odom: np.ndarray | None
    track: Track | None = None
    frame: Frame | None = None


def odometry_move(since: np.ndarray | None, now: np.ndarray | None) -> np.ndarray | None:
    """Robot-frame motion from odometry pose ``since`` to ``now`` (``None`` if either is)."""
    return None if since is None or now is None else relative(since, now)


@dataclass(eq=False)
class Drive:
    """The hypotheses over a drive and their evidence: ``tracks``, the window's ``frames``, the
    odometry ``travel`` (m), the pending search ``job`` and ``twin`` check (not pickled), the
    composite's scans, the speed before a loss, every keyframe's key (scores there are kept)."""

    tracks: list[Track] = field(default_factory=list)
    frames: list[Frame] = field(default_factory=list)
    next_key: int = 0
    travel: float = 0.0
    job: Job | None = None
    twin: Job | None = None
    history: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = field(default_factory=list)
    speed: np.ndarray | None = None
    keyframes: list[int] = field(default_factory=list)

    def __getstate__(self) -> dict[str, Any]:
        return {**self.__dict__, "job": None, "twin": None}

    def __setstate__(self, state: dict[str, Any]) -> None:
        # pickled with a weight per keyframe (every one 1): the keys are the keyframes
        state.setdefault("keyframes", list(state.pop("weights", {})))
        self.__dict__.update(state)

    def move(self, delta: np.ndarray, step: float) -> None:
        """Move every track by the odometry increment ``delta`` (robot frame, ``step`` m)."""
        self.travel += step
        for t in self.tracks:
            t.pose = compose(t.pose, delta)

    def add(self, frame: Frame, g: GlobalConfig) -> None:
        """Add a frame; the window keeps the recent ones (:func:`window`)."""
        self.next_key = frame.key + 1
        self.frames = window([*self.frames, frame], g)
        if frame.odom is not None:
            self.keyframes.append(frame.key)

    def observe(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None, g: GlobalConfig
    ) -> Frame | None:
        """Add a scan's frame: without odometry a plain-scan frame (returned); with odometry
        pose ``odom`` a keyframe when one is due (:func:`frame_due`), else none (a standing
        robot's scans repeat its keyframe's walls, for a wrong place as for the true one)."""
        if odom is not None and not frame_due(self.frames, odom, self.travel):
            return None
        frame = make_frame(self.next_key, ranges, angles, odom, self.travel, g)
        self.add(frame, g)
        return frame if odom is None else None

    def evidence_keys(self, g: GlobalConfig) -> list[int]:
        """The frames the decision sums over: every keyframe of the drive, or without odometry
        the window's plain scans (consecutive scans see nearly the same)."""
        win = window(self.frames, g)
        return [f.key for f in win] if win and win[-1].odom is None else list(self.keyframes)

    def composite(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray]:
        """The scan the search matches: this one, or with odometry the last few fused."""
        if odom is None or COMPOSITE_SCANS <= 1:
            self.history = []
            return ranges, angles
        self.history = [
            h
            for h in self.history[-(COMPOSITE_SCANS - 1) :]
            if np.hypot(*(h[2][:2] - odom[:2])) <= COMPOSITE_TRAVEL
        ]
        self.history.append((ranges, angles, odom.copy()))
        if len(self.history) == 1:
            return ranges, angles
        inc = float(np.median(np.abs(np.diff(angles)))) if angles.size > 1 else 0.0
        bins = COMPOSITE_BINS
        if inc > 0.0:  # no finer than the laser's beams (holes would split every polyline)
            bins = int(min(bins, max(8, np.floor(2.0 * np.pi / inc + 1e-6))))
        return composite_scan(self.history, bins)


def make_frame(
    key: int,
    ranges: np.ndarray,
    angles: np.ndarray,
    odom: np.ndarray | None,
    travel: float,
    g: GlobalConfig,
) -> Frame:
    """A :class:`Frame` of one scan (``odom`` its odometry pose or ``None``: a plain scan)."""
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    sel = subsample(np.nonzero(np.isfinite(r))[0], g.verify_beams)
    ranges, angles = r[sel].copy(), a[sel].copy()
    points = np.column_stack([ranges * np.cos(angles), ranges * np.sin(angles)])
    points = subsample(points, gs.SUPPORT_POINTS)
    odom = None if odom is None else np.asarray(odom, dtype=np.float64).copy()
    return Frame(key, ranges, angles, points.copy(), odom, float(travel))


def frame_due(frames: list[Frame], odom: np.ndarray, travel: float) -> bool:
    """Whether a scan at odometry pose ``odom`` and drive travel ``travel`` becomes a keyframe:
    the first, or :data:`EVIDENCE_SPACING` driven or :data:`EVIDENCE_TURN` turned since."""
    if not frames or frames[-1].odom is None:
        return True
    last = frames[-1]
    turn = abs(float(wrap_angle(float(odom[2]) - float(last.odom[2]))))
    return travel - last.travel >= EVIDENCE_SPACING or turn >= EVIDENCE_TURN


def window(frames: list[Frame], g: GlobalConfig) -> list[Frame]:
    """The frames of the window: keyframes within ``evidence_span`` metres of the newest (at
    most :data:`EVIDENCE_FRAMES`), plain scans the last :data:`SCAN_WINDOW`."""
    if not frames:
        return []
    if frames[-1].odom is None:
        return [f for f in frames if f.odom is None][-SCAN_WINDOW:]
    newest = frames[-1].travel
    out = [f for f in frames if f.odom is not None and newest - f.travel <= g.evidence_span]
    return out[-EVIDENCE_FRAMES:]


def judged(frames: list[Frame]) -> list[int]:
    """Keys of the window's frames a track must be scored on to be judged: every keyframe
    (back-scoring reaches those before it was found), or without odometry the newest scan
    only (nothing carries a place found later back to an earlier scan)."""
    return [frames[-1].key] if frames and frames[-1].odom is None else [f.key for f in frames]


def loglik(cost: float) -> float:
    """A frame's log-likelihood (nats) from its beam cost, clipped at :data:`EVIDENCE_CLIP`."""
    return -EFFECTIVE_BEAMS * (min(cost, EVIDENCE_CLIP) - gs.COST_FLOOR)


def frame_cost(
    index: ViewIndex, pose: np.ndarray, f: Frame, config: ShapeConfig, g: GlobalConfig
) -> tuple[float, float]:
    """The beam cost of ``pose`` on frame ``f``'s beams (short returns graded by
    ``evidence_short_scale``) and the unseen place's cost there, which rises with the mean
    range of the map's walls (``GlobalConfig.null_slope``)."""
    if f.ranges.size == 0:
        return EVIDENCE_CLIP, g.null_cost
    assert index.sensor is not None
    m = gs.beam_model(config, g, short_scale=g.evidence_short_scale)
    pred, landed = index.sensor.predict(pose, f.ranges, f.angles, m)
    cost = beam_fractions(f.ranges, pred, m, landed).cost(m)
    if g.null_slope <= 0.0:
        return cost, g.null_cost
    reach = float(np.mean(np.where(np.isfinite(pred), pred, m.max_range)))
    return cost, min(EVIDENCE_CLIP, g.null_cost + g.null_slope * max(0.0, reach - NULL_REACH))


def pair_ms(index: ViewIndex, g: GlobalConfig) -> float:
    """Work (reference ms) of scoring one track on one keyframe: a polish and the beams."""
    polish = gs.WORK_MS["polish_call"] + gs.polish_ms(gs.SUPPORT_POINTS)
    return polish + gs.beams_ms(index, g, g.verify_beams)


def rescore(
    index: ViewIndex,
    tracks: list[Track],
    ranges: np.ndarray,
    angles: np.ndarray,
    P: Configuration,
    config: ShapeConfig,
    g: GlobalConfig,
    limit: float,
    scan: Frame | None,
) -> float:
    """Fit each track (best first) to this scan and verify it within ``limit`` reference ms;
    return the work spent. With odometry a polish absorbs its error; without, a refinement
    follows the robot, and the verification is the track's evidence on the frame ``scan``."""
    if not tracks:
        return 0.0
    sp = gs.support_sample(P)
    odometry = scan is None
    fit_ms = gs.polish_ms(len(sp)) if odometry else gs.refine_ms(index)
    each = fit_ms + gs.verify_ms(index, g)
    n = len(tracks) if not np.isfinite(limit) else max(1, min(len(tracks), int(limit // each)))
    chosen = sorted(tracks, key=lambda t: t.hyp.cost)[:n]
    if len(sp) == 0:
        return n * each
    poses = np.vstack([t.pose for t in chosen])
    if odometry:
        assert index.sensor is not None
        fitted, _ = index.sensor.polish(poses, sp, gs.FINE_SCALE, prior=RESCORE_PRIOR)
    else:
        fitted = gs.refine(index, poses, sp, config)
    for t, p in zip(chosen, fitted, strict=True):
        t.hyp = gs.verify(index, p, ranges, angles, P, config, g)
        t.pose = t.hyp.pose.copy()
        if scan is not None:
            t.record(scan.key, t.hyp.cost, t.hyp.pose)
    return n * each


def backfill(
    index: ViewIndex,
    tracks: list[Track],
    frames: list[Frame],
    odom_now: np.ndarray,
    config: ShapeConfig,
    g: GlobalConfig,
    limit: float,
    first: Track | None = None,
) -> float:
    """Score the tracks on the window's keyframes they lack, newest first and breadth first
    (``first``, a winner on probation, before the others), within ``limit`` reference ms (at
    least one score); return the work spent. Poses older than the window are forgotten."""
    keys = {f.key for f in frames}
    odom_of = {f.key: f.odom for f in frames}
    for t in tracks:
        for k in [k for k in t.at if k not in keys]:
            del t.at[k]  # the score there is kept (Drive.keyframes)
    kf = [f for f in frames if f.odom is not None]
    if not kf:
        return 0.0
    assert index.sensor is not None
    each = pair_ms(index, g)
    spent = 0.0
    ranked = sorted(tracks, key=lambda t: (t is not first, -len(t.ll), t.hyp.cost))
    for f in reversed(kf):
        for t in ranked:
            if f.key in t.ll:
                continue
            if spent >= limit:
                return spent
            # carried by the odometry from the next keyframe it was scored on, else from now
            newer = [k for k in t.at if k > f.key]
            base, odom = (t.at[min(newer)], odom_of[min(newer)]) if newer else (t.pose, odom_now)
            start = compose(base, relative(odom, f.odom))
            polished, _ = index.sensor.polish(
                start[None, :], f.points, gs.FINE_SCALE, prior=RESCORE_PRIOR
            )
            pose = polished[0]
            cost, null = frame_cost(index, pose, f, config, g)
            if not t.ll:
                # first keyframe: a wide polish and the pose as given too, for a place degrees off
                wide, _ = index.sensor.polish(start[None, :], f.points, gs.FINE_SCALE, WIDE_POLISH)
                for alt in (wide[0], start):
                    c, n = frame_cost(index, alt, f, config, g)
                    if c < cost:
                        pose, cost, null = alt, c, n
                spent += 0.5 * gs.polish_ms(len(f.points)) + 2 * each
            t.record(f.key, cost, pose)
            t.null[f.key] = null
            spent += each
    return spent


def merge(
    tracks: list[Track],
    hyps: list[gs.Hypothesis],
    move: np.ndarray | None,
    keep: int,
    scored: Frame | None = None,
) -> list[Track]:
    """Add the best ``keep`` of a finished search's hypotheses (``move``: the odometry motion
    since its scan) to ``tracks`` unless one holds the pose already (found once more).
    ``scored``: the plain-scan frame it ran on, still in the window, where a place's
    verification is its evidence (unscored it would count as the leader's)."""
    out = list(tracks)
    counted: list[Track] = []
    for h in hyps[:keep]:
        pose = compose(h.pose, move) if move is not None else np.asarray(h.pose, dtype=float)
        # without odometry the robot may have turned and a fit slid off: a place found again
        # within a place's distance is that track, and follows the search's better fit
        if move is None and scored is not None:
            dist, turn = gs.DISTINCT_DISTANCE, TURN_BETWEEN_SCANS
        else:
            dist, turn = 0.3, 0.15
        held = [t for t in out if gs.near(t.pose, pose, dist, turn)]
        for t in held:
            if t not in counted:
                t.found += 1
                counted.append(t)
            if scored is not None and h.cost < t.hyp.cost:
                t.pose, t.hyp = pose.copy(), h
                t.record(scored.key, h.cost, pose)
        if held:
            continue
        track = Track(pose.copy(), dataclasses.replace(h, pose=pose.copy()))
        if scored is not None:
            track.record(scored.key, h.cost, pose)
        out.append(track)
    return out


def prune(
    tracks: list[Track],
    frames: list[Frame],
    keys: list[int],
    leader: Track | None,
    g: GlobalConfig,
    lost: bool = False,
) -> list[Track]:
    """The tracks to keep: one trailing the ``leader`` on 3+ common frames of ``keys``, or the
    unseen place on 3+ of the window's (its cost there, as the decision's), by EVIDENCE_DROP
    nats goes; of the rest the best ``keep`` judged on the whole window, ``keep`` being judged."""
    recent = {f.key for f in frames} if lost else set(keys)

    def dropped(t: Track) -> bool:
        now = [k for k in keys if k in t.ll and k in recent]  # where the unseen place is judged
        null = sum(-EFFECTIVE_BEAMS * (t.null.get(k, g.null_cost) - gs.COST_FLOOR) for k in now)
        if len(now) >= 3 and sum(t.ll[k] for k in now) < null - EVIDENCE_DROP:
            return True
        if leader is None or t is leader:
            return False
        both = [k for k in keys if k in leader.ll and k in t.ll]
        lead, own = sum(leader.ll[k] for k in both), sum(t.ll[k] for k in both)
        return len(both) >= 3 and lead - own > EVIDENCE_DROP

    live = [t for t in tracks if not dropped(t)]
    win = judged(frames)
    full = [t for t in live if all(k in t.ll for k in win)]

    done = sorted(full, key=lambda t: -sum(t.ll.get(k, 0.0) for k in keys))
    done.sort(key=lambda t: t is not leader)  # the leader first
    pending = sorted((t for t in live if t not in full), key=lambda t: (-len(t.ll), t.hyp.cost))
    out: list[Track] = []
    for group in (done, pending):
        before = len(out)
        for t in group:
            if len(out) - before >= g.keep:
                break
            if not any(gs.near(t.pose, o.pose) for o in out):
                out.append(t)
    return out


def candidates(tracks: list[Track], first: Track | None = None, k: int = 5) -> np.ndarray:
    """The first ``k`` tracks, ``first`` first, as rows ``[x, y, theta, cost]``."""
    order = ([first] if first is not None else []) + [t for t in tracks if t is not first]
    rows = [[*map(float, t.pose), float(t.hyp.cost)] for t in order[:k]]
    return np.array(rows, dtype=np.float64).reshape(-1, 4)


#: Earlier versions' name of a frame (a localiser state pickled by them names it).
Keyframe = Frame
