"""Pose hypotheses kept across scans while the pose is unknown (global localisation, a
kidnapped or lost robot): :class:`Track`, and the pieces of the budgeted multi-hypothesis
search that :class:`service.core.reloc.global_localization.GlobalShapeLocalizer` runs when
``GlobalConfig.search_budget_ms`` is set:

* :func:`rescore` — every kept hypothesis, moved by the odometry since the last scan, is fitted
  locally to the new scan and verified beam by beam
  (:func:`service.core.sensor.pose_scoring.verify`), best first, within a share of the per-scan
  budget. Evidence thus accumulates on every scan for every hypothesis, not only for those a search
  happens to find again.
* :func:`merge` — a search that was spread over several scans delivers hypotheses for the
  scan it started on; they are moved by the odometry since then and join the kept ones.
* :class:`Job` — a search (:func:`service.core.reloc.global_search.search_steps` or
  :func:`~service.core.reloc.global_search.self_similar_steps`) in progress, advanced by
  :func:`advance` within what is left of the scan's budget.

Work is counted in the deterministic reference milliseconds of
:data:`service.core.reloc.global_search.WORK_MS`, so the same scans give the same poses on any
machine and under any load.
"""

from __future__ import annotations

from collections.abc import Generator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from service.core.pose import compose, invert
from service.core.reloc.global_config import GlobalConfig
from service.core.reloc.global_search import _near, _refine, _verify_ms, polish_ms, refine_ms
from service.core.reloc.view_index import ViewIndex
from service.core.sensor.pose_scoring import Hypothesis, _polish, _subsample, verify
from service.core.shapes.configuration import Configuration
from service.core.tracking.localizer import ShapeConfig

#: A hypothesis of this scan continues a track of the last one within this distance (m) and
#: heading change (rad): between two scans a robot may move a few decimetres and turn a lot.
ASSOCIATE = (0.6, 1.0)
#: Work (reference ms) of the tracker's confirmation of a winner: a tracker update from a
#: fresh reset, measured 10 / 21 ms median on the office's metric / schematic map.
CONFIRM_MS = 20.0


@dataclass(eq=False)
class Track:
    """A hypothesis followed across scans: its pose and the costs of the last scans (1.0
    stands for a scan on which it was not among the verified hypotheses). ``hyp`` is its
    latest verification with ``cost`` replaced by the decision's (windowed) cost; ``wins``
    consecutive scans it was the best; ``age`` scans it was re-scored on (budgeted search);
    ``twin_ok`` the outcome of its self-similarity check (``None``: not checked);
    ``twin_held`` whether a check of it found a twin that then joined the hypotheses (so the
    drive's evidence judges the two on the same keyframes); ``found`` how many searches found
    it (the one it came from, and later ones that found it again); ``refined`` the newest
    keyframe when :mod:`service.core.reloc.window_refine` last placed it; ``twin`` the kept track
    holding the twin its check found (``GlobalConfig.twin_hold_kept``)."""

    pose: np.ndarray
    costs: list[float]
    hyp: Hypothesis
    wins: int = 0
    age: int = 0
    twin_ok: bool | None = None
    twin_held: bool = False
    found: int = 1
    ev: dict[int, float] = field(default_factory=dict)
    ev_pose: dict[int, np.ndarray] = field(default_factory=dict)
    ev_odom: dict[int, np.ndarray] = field(default_factory=dict)
    #: the newest keyframe key when a refinement last placed it (``GlobalConfig.
    #: verdict_refine``; -1: never)
    refined: int = -1
    #: the kept track that holds the twin a check of this one found
    #: (``GlobalConfig.twin_hold_kept``; ``None``: none)
    twin: Track | None = None


@dataclass(eq=False)
class Job:
    """A search in progress: its step generator and the odometry pose of the scan it started
    on (``None`` without odometry); ``track`` the track a self-similarity check is for, and
    ``cost`` that track's cost on the check's scan."""

    steps: Generator[float, None, Any]
    odom: np.ndarray | None
    track: Track | None = None
    cost: float = 0.0


def advance(job: Job, spent: float, budget: float) -> tuple[float, bool, Any]:
    """Run ``job`` until the scan's work ``spent`` reaches ``budget`` (at least one step, so
    a search always progresses). Returns ``(spent, done, result)``."""
    while True:
        try:
            w = next(job.steps)
        except StopIteration as stop:
            return spent, True, stop.value
        spent += w
        if spent >= budget:
            return spent, False, None


def odometry_move(since: np.ndarray | None, now: np.ndarray | None) -> np.ndarray | None:
    """Robot-frame motion from odometry pose ``since`` to ``now`` (``None`` if either is)."""
    if since is None or now is None:
        return None
    return compose(invert(since), now)


def rescore(
    index: ViewIndex,
    tracks: list[Track],
    ranges: np.ndarray,
    angles: np.ndarray,
    P: Configuration,
    config: ShapeConfig,
    gconfig: GlobalConfig,
    limit: float,
    odometry: bool,
) -> float:
    """Fit each track (best first) to this scan and verify it, while the work stays within
    ``limit`` (reference ms); a track left out this scan records a miss (cost 1.0). With
    odometry the tracks were moved by it and a polish on the distance field (+-0.1 m,
    +-0.04 rad) absorbs its error; without, the point-to-line refinement (wider basin) has to
    follow the robot's motion. With odometry the moved pose is the polish's motion prior
    (``gconfig.rescore_prior``), and with ``gconfig.rescore_keep_moved`` the moved pose is
    verified too and kept when it explains the scan better than the polished one. Returns
    the work spent."""
    if not tracks:
        return 0.0
    pts = np.vstack([f.points for f in P.features]) if P.features else np.zeros((0, 2))
    sp = _subsample(pts, gconfig.support_points)
    fit_ms = polish_ms(len(sp)) if odometry else refine_ms(index)
    both = odometry and gconfig.rescore_keep_moved
    each = fit_ms + _verify_ms(index, gconfig) * (2 if both else 1)
    n = max(1, min(len(tracks), int(limit // each)))
    order = sorted(range(len(tracks)), key=lambda k: tracks[k].hyp.cost)
    chosen = [tracks[k] for k in order[:n]]
    for t in tracks:
        if t not in chosen:
            t.costs.append(1.0)
    if len(sp) == 0:
        for t in chosen:
            t.costs.append(1.0)
        return n * each
    poses = np.vstack([t.pose for t in chosen])
    if odometry:
        fitted, _ = _polish(index, poses, sp, gconfig.fine_scale, prior=gconfig.rescore_prior)
    else:
        fitted = _refine(index, poses, sp, config, gconfig)
    for k, (t, p) in enumerate(zip(chosen, fitted, strict=True)):
        h = verify(index, p, ranges, angles, P, config, gconfig)
        if both:
            moved = verify(index, poses[k], ranges, angles, P, config, gconfig)
            if moved.cost < h.cost:
                h = moved
        t.pose = h.pose.copy()
        t.hyp = h
        t.costs.append(h.cost)
        t.age += 1
    return n * each


def merge(
    tracks: list[Track],
    hyps: list[Hypothesis],
    move: np.ndarray | None,
    keep: int,
    refound: list[tuple[Track, np.ndarray]] | None = None,
) -> list[Track]:
    """Add the best ``keep`` of a finished search's hypotheses (found on an earlier scan;
    ``move`` the robot-frame odometry motion since, or ``None``) to ``tracks`` unless one
    already holds that pose. New tracks carry the search's cost and age 0: they are decided
    on only after a re-scoring on a scan of their own; a track the search found again counts
    it in ``found``, and ``(track, the search's pose moved to now)`` is appended to
    ``refound`` if given (:func:`service.core.reloc.evidence.adopt_refound`)."""
    out = list(tracks)
    found: list[Track] = []
    for h in hyps[:keep]:
        pose = compose(h.pose, move) if move is not None else np.asarray(h.pose, dtype=float)
        held = [t for t in out if _near(t.pose, pose)]
        if held:
            for t in held:
                if t not in found:
                    t.found += 1
                    found.append(t)
                    if refound is not None:
                        refound.append((t, pose.copy()))
            continue
        hyp = Hypothesis(
            pose=pose.copy(),
            cost=h.cost,
            hit=h.hit,
            violation=h.violation,
            explained=h.explained,
            short=h.short,
        )
        out.append(Track(pose.copy(), [h.cost], hyp))
    return out


def prune(tracks: list[Track], keep: int) -> list[Track]:
    """The ``keep`` best tracks (by decision cost), one per pose (a track that converged onto a
    better one's pose is dropped)."""
    out: list[Track] = []
    for t in sorted(tracks, key=lambda t: (t.hyp.cost, -t.age)):
        if len(out) >= keep:
            break
        if any(_near(t.pose, o.pose) for o in out):
            continue
        out.append(t)
    return out


def candidates(tracks: list[Track], k: int = 5) -> np.ndarray:
    """The best ``k`` tracks as ``(k, 4)`` rows ``[x, y, theta, cost]`` (for the wire)."""
    rows = [[*map(float, t.pose), float(t.hyp.cost)] for t in tracks[:k]]
    return np.array(rows, dtype=np.float64).reshape(-1, 4)
