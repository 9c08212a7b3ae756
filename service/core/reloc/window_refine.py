"""A fair verdict on the drive's keyframes: every contender placed where the drive's beams
fit it best (``GlobalConfig.verdict_refine``).

Why. Two verdicts compare hypotheses on the drive's keyframes: the evidence rule naming a
winner, and the end of a single-scan winner's probation (``GlobalConfig.probation_verdict``;
:func:`service.core.reloc.evidence.beaten`). A hypothesis' keyframe poses were placed by the
odometry and polished on the map's distance field (:func:`service.core.reloc.evidence.backfill`);
a probation winner's are the tracker's, fitted scan by scan. On a floor plan that polish can
settle off the place the beams fit: furniture returns near the walls pull it, and along a
corridor little in the field pins the axis. A hypothesis held 0.15-0.2 m off its place then
scores like a wrong place. Tuning building 62 (floor plan, start 29): the rule named a place
15 m off at a mean of 0.598 over 20 keyframes by 0.152 over the true place, whose hypothesis
sat 0.17 m off at 0.750 (0.398 once placed). Held-out building 1001 (start 17): the true
place's hypothesis sat 0.17-0.21 m off on all 20 keyframes of a probation and scored 0.357
against the winner's 0.284 (a congruent room 9 m away, turned 90 degrees), the beams at the
true pose 0.13; a wide polish from the hypothesis' own poses stayed in the same trap, so the
probation passed and the wrong room was published for 10 m.

What. Before either verdict, the winner and its closest distinct alternatives (at most
``verdict_refine_tracks``, each within ``evidence_drop`` of the winner's mean on the keyframes
both were scored on) are each moved as one rigid body -- every keyframe pose of the track by
the same small rotation about their centroid and translation -- to where the mean beam cost
over its keyframes (:func:`service.core.reloc.evidence.frame_cost`, the verdict's own measure) is
lowest: a pattern search (+-x, +-y, +-theta; steps of 0.1 m / 0.02 rad, then 0.04 m /
0.008 rad) probing on at most eight of its keyframes spread over the window, the shift found
then scored on all of them and kept only if it explains them better. One shift for the whole
window keeps the odometry's shape of the drive: a wrong place cannot bend the drive to fit
it, the true place's constant offset is removed. The keyframe scores and poses found
replace the track's, and the tracks are marked ``refined`` together once all are done (the
rule then decides on them). The work is counted in reference ms and spread over scans
(:func:`advance`); the state is plain data, so a localiser persisted mid-refinement resumes
it.

Units: metres, radians; poses ``[x, y, theta]`` in the map frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from service.core.reloc.evidence import Keyframe, _common_means, frame_cost
from service.core.reloc.global_search import _distinct, beams_ms
from service.core.reloc.hypotheses import Track
from service.core.types import wrap_angle

if TYPE_CHECKING:
    from service.core.reloc.global_config import GlobalConfig
    from service.core.reloc.view_index import ViewIndex
    from service.core.tracking.localizer import ShapeConfig

#: the pattern search's step sizes (m, rad), coarse to fine, and the moves at each at most
#: (the shift stays within 0.38 m / 0.076 rad)
_LEVELS = ((0.1, 0.02, 3), (0.04, 0.008, 2))
#: the search probes a shift on at most this many of the track's keyframes, evenly spread
#: over the window; the shift found is then scored on all of them
_PROBE_FRAMES = 8
#: a move, and the shift found, must lower the mean cost by at least this much: along a
#: corridor the beams' cost hardly changes with the shift along its axis, and a search that
#: took every last improvement slid the true place's hypothesis 0.2 m along it (tuning
#: building 70, start 42)
_MIN_GAIN = 0.01
#: the probe directions: +-x, +-y, +-theta in units of the level's steps
_DIRS = np.array(
    [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64
)


@dataclass(eq=False)
class Refinement:
    """The state of a verdict's refinement (plain data: picklable). ``queue`` the tracks to
    refine (the winner first); ``frames`` the keyframes judged, frozen at the start; for the
    track being refined (``queue[i]``): its keyframe keys and the few the search probes on,
    its mean over all of them before (``base``), the centroid the rotation turns about, the
    current ``shift`` and its mean cost on the probed keyframes ``cur``, the step size
    ``level``, ``moves`` made at it, and this round's probes."""

    queue: list[Track]
    frames: list[Keyframe]
    i: int = 0
    keys: list[int] = field(default_factory=list)
    poses: dict[int, np.ndarray] = field(default_factory=dict)
    probe_keys: list[int] = field(default_factory=list)
    base: float = float("inf")
    pivot: np.ndarray = field(default_factory=lambda: np.zeros(2))
    shift: np.ndarray = field(default_factory=lambda: np.zeros(3))
    cur: float = float("inf")
    level: int = 0
    moves: int = 0
    probe: int = 0
    round_best: float = float("inf")
    round_shift: np.ndarray | None = None
    started: bool = False


def start(best: Track, tracks: list[Track], frames: list[Keyframe], g: GlobalConfig) -> Refinement:
    """The refinement of ``best`` and its closest distinct alternatives (at most
    ``verdict_refine_tracks``, ranked by their mean over the keyframes both were scored on,
    each within ``evidence_drop`` of ``best``'s and scored on at least
    ``evidence_drop_frames`` of them)."""
    need = min(g.evidence_drop_frames, len(frames))
    rivals: list[tuple[float, int, Track]] = []
    for n, t in enumerate(tracks):
        if t is best or not _distinct(t.pose, best.pose, g):
            continue
        mine, theirs, common = _common_means(best, t, frames)
        if common >= max(need, 1) and theirs - mine < g.evidence_drop:
            rivals.append((theirs - mine, n, t))
    rivals.sort(key=lambda x: (x[0], x[1]))
    queue = [best, *(t for _, _, t in rivals[: g.verdict_refine_tracks])]
    return Refinement(queue=queue, frames=list(frames))


def moved(pose: np.ndarray, pivot: np.ndarray, shift: np.ndarray) -> np.ndarray:
    """``pose`` moved rigidly: turned by ``shift[2]`` about ``pivot`` and translated by
    ``shift[:2]``."""
    c, s = np.cos(shift[2]), np.sin(shift[2])
    d = pose[:2] - pivot
    xy = pivot + np.array([c * d[0] - s * d[1], c * d[1] + s * d[0]]) + shift[:2]
    return np.array([xy[0], xy[1], wrap_angle(float(pose[2] + shift[2]))])


def advance(
    ref: Refinement,
    index: ViewIndex,
    config: ShapeConfig,
    g: GlobalConfig,
    spent: float,
    budget: float,
) -> tuple[float, bool]:
    """Run the refinement until the scan's work ``spent`` reaches ``budget`` (at least one
    probe, so it always progresses). Returns ``(spent, done)``; done, every queued track's
    keyframe scores and poses are those at its best shift."""
    by_key = {f.key: f for f in ref.frames}
    each = beams_ms(index, g, g.verify_beams)
    while ref.i < len(ref.queue):
        t = ref.queue[ref.i]
        if not ref.started:
            ref.keys = [k for k in by_key if k in t.ev and k in t.ev_pose]
            ref.started = True
            ref.shift = np.zeros(3)
            ref.level = ref.moves = ref.probe = 0
            ref.round_best, ref.round_shift = float("inf"), None
            if not ref.keys:
                ref.i += 1
                ref.started = False
                continue
            ref.poses = {k: t.ev_pose[k].copy() for k in ref.keys}
            ref.pivot = np.mean([ref.poses[k][:2] for k in ref.keys], axis=0)
            pick = np.unique(np.linspace(0, len(ref.keys) - 1, _PROBE_FRAMES).round().astype(int))
            ref.probe_keys = [ref.keys[j] for j in pick]
            ref.cur = float(np.mean([t.ev[k] for k in ref.probe_keys]))
            ref.base = float(np.mean([t.ev[k] for k in ref.keys]))
        if ref.level < len(_LEVELS):
            step_xy, step_th, _ = _LEVELS[ref.level]
            cand = ref.shift + _DIRS[ref.probe] * np.array([step_xy, step_xy, step_th])
            mean = _mean_cost(ref, ref.probe_keys, cand, by_key, index, config, g)[0]
            spent += each * len(ref.probe_keys)
            if mean < ref.round_best:
                ref.round_best, ref.round_shift = mean, cand
            ref.probe += 1
            if ref.probe == len(_DIRS):
                _end_round(ref)
        else:
            # the shift found, scored on all the track's keyframes: kept if it explains them
            # better than the poses the track had
            if np.any(ref.shift != 0.0):
                mean, costs = _mean_cost(ref, ref.keys, ref.shift, by_key, index, config, g)
                spent += each * len(ref.keys)
                if mean < ref.base - _MIN_GAIN:
                    _write(ref, t, costs)
            ref.i += 1
            ref.started = False
        if spent >= budget and ref.i < len(ref.queue):
            return spent, False
    newest = max((f.key for f in ref.frames), default=-1)
    for t in ref.queue:
        t.refined = newest  # all of them together: the verdict compares them
    return spent, True


def _mean_cost(
    ref: Refinement,
    keys: list[int],
    shift: np.ndarray,
    by_key: dict[int, Keyframe],
    index: ViewIndex,
    config: ShapeConfig,
    g: GlobalConfig,
) -> tuple[float, list[float]]:
    """The mean beam cost of the refined track over its keyframes ``keys`` with its poses
    moved by ``shift``, and the costs."""
    costs = [
        frame_cost(index, moved(ref.poses[k], ref.pivot, shift), by_key[k], config, g) for k in keys
    ]
    return float(np.mean(costs)), costs


def _end_round(ref: Refinement) -> None:
    """After the six probes: move to the best if it improved, else go one step size finer."""
    if ref.round_shift is not None and ref.round_best < ref.cur - _MIN_GAIN:
        ref.shift, ref.cur = ref.round_shift, ref.round_best
        ref.moves += 1
        if ref.moves >= _LEVELS[ref.level][2]:
            ref.level, ref.moves = ref.level + 1, 0
    else:
        ref.level, ref.moves = ref.level + 1, 0
    ref.probe = 0
    ref.round_best, ref.round_shift = float("inf"), None


def _write(ref: Refinement, t: Track, costs: list[float]) -> None:
    """Write the shift found into the track: its keyframe poses and scores (of the keyframes
    it still holds: the window may have moved on meanwhile), and its pose."""
    for k, c in zip(ref.keys, costs, strict=True):
        if k in t.ev:
            t.ev_pose[k] = moved(ref.poses[k], ref.pivot, ref.shift)
            t.ev[k] = float(c)
    t.pose = moved(t.pose, ref.pivot, ref.shift)
