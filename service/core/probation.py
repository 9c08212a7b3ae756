"""The probation of a search's winner (``GlobalConfig.probation_travel``), as a mixin of
:class:`service.core.drive_search.DriveSearch`: the winner is tracked over a stretch of
driving while the search's hypotheses are kept, moved by the odometry and judged on the
drive's keyframes, before it is published; it fails where tracking would have ended, and a
single-scan winner is judged at its end (``probation_verdict``, after the refinement of
:mod:`service.core.window_refine`)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from service.core import evidence as ev_mod
from service.core import hypotheses as hyp_mod
from service.core import window_refine as wr_mod
from service.core.configuration import scan_configuration
from service.core.global_search import ambiguity, search_steps
from service.core.hypotheses import Track
from service.core.pose import compose, invert
from service.core.types import Estimate

if TYPE_CHECKING:
    from service.core.global_config import GlobalConfig
    from service.core.localizer import ShapeConfig
    from service.core.view_index import ViewIndex


@dataclass(eq=False)
class Probation:
    """A search's winner being tracked before it is published (``GlobalConfig.
    probation_travel``): the track it came from (kept with the others, moved by the
    odometry), the travel ``left``, and the decision's ambiguity and extras."""

    track: Track
    left: float
    ambiguity: float
    extras: dict[str, float] = field(default_factory=dict)
    rejected: int = 0
    #: searches finished during the probation (``GlobalConfig.probation_searches``)
    searches: int = 0
    #: the confirmed pose and the odometry reading it was confirmed on (the reference the
    #: tracked pose is checked against, ``GlobalConfig.probation_slide``)
    start: np.ndarray | None = None
    start_odom: np.ndarray | None = None
    #: odometry travel (m) of the scans the tracker accepted since its last rejection
    #: (``GlobalConfig.probation_relock``)
    relock: float = 0.0
    #: the verdict's refinement in progress (``GlobalConfig.verdict_refine``)
    refine: wr_mod.Refinement | None = None
    #: the tracks kept when the probation began: the hold through rejections
    #: (:meth:`ProbationSteps._drive_holds`) weighs the winner against these only; places a
    #: probation search finds later are the verdict's to judge at the probation's end
    rivals: tuple[Track, ...] = ()


class ProbationSteps:
    """Mixin of :class:`~service.core.drive_search.DriveSearch`: a winner's probation (see
    the module docstring)."""

    # provided by the localiser and the search
    gconfig: GlobalConfig
    config: ShapeConfig
    index: ViewIndex
    _tracks: list[Track]
    _history: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    _job: hyp_mod.Job | None
    _twin_job: hyp_mod.Job | None
    _rule_refine: wr_mod.Refinement | None
    _confirm_next: bool
    _last_odom: np.ndarray | None
    work_ms: float
    _frames: list[ev_mod.Keyframe]
    _probation: Probation | None
    _searching: bool
    _search_status: str
    _since_fix: int
    _unfit: int
    tracker: Any
    # and the methods _seeds, _unresolved, _odom_copy, _move_kept, _add_keyframe, _backfill,
    # _advance_search, _evidence_won
    _seeds: Callable[[], list[np.ndarray]]
    _unresolved: Callable[..., Estimate]
    _odom_copy: Callable[[], np.ndarray | None]
    _move_kept: Callable[[np.ndarray], float]
    _add_keyframe: Callable[[np.ndarray, np.ndarray, np.ndarray], None]
    _backfill: Callable[[np.ndarray, float], float]
    _advance_search: Callable[..., tuple[float, Any]]
    _evidence_won: Callable[..., bool]

    def _probation_due(self, extras: dict[str, float]) -> bool:
        """Whether a winner the tracker just confirmed goes on probation first: with
        odometry, ``probation_travel`` > 0, and not recovered next to the lost track."""
        return (
            self.gconfig.probation_travel > 0.0
            and self._last_odom is not None
            and "near_track" not in extras
        )

    def _begin_probation(
        self, best: Track, est: Estimate, amb: float, extras: dict[str, float]
    ) -> Estimate:
        """Track ``best`` (the tracker is already reset to it and accepted this scan) while
        the search's hypotheses are kept and moved by the odometry; publish the search's
        status with the tracked pose as the best guess."""
        self._probation = Probation(
            best,
            self.gconfig.probation_travel,
            amb,
            dict(extras),
            start=est.pose.copy(),
            start_odom=self._odom_copy(),
            rivals=tuple(self._tracks),
        )
        # the pending jobs belong to earlier scans; a failed probation starts a new search
        self._job = None
        self._twin_job = None
        self._rule_refine = None
        self._confirm_next = False
        return self._on_probation(est)

    def _on_probation(self, est: Estimate) -> Estimate:
        p = self._probation
        assert p is not None
        # the winner follows the tracker (moved by the odometry with the others before)
        p.track.pose = est.pose.copy()
        est.status = self._search_status  # type: ignore[assignment]
        est.ambiguity = p.ambiguity
        est.extras["probation"] = max(0.0, p.left)
        est.hypotheses = len(self._tracks)
        order = [p.track, *(t for t in self._tracks if t is not p.track)]
        est.candidates = hyp_mod.candidates(order)
        return est

    def _slide_check(self, r: np.ndarray, a: np.ndarray, est: Estimate) -> None:
        """``GlobalConfig.probation_slide``: put the tracker back on the dead-reckoned pose
        (the confirmed pose moved by the odometry since) when the tracked one has moved away
        from it and lets clearly more of this scan's beams through the map's walls
        (:meth:`service.core.localizer.ShapeLocalizer.violations`). Slow slides like that,
        a few cm per scan, each look fine against the scan's own odometry prior; only the
        probation has a reference that is not itself the tracker's output."""
        p = self._probation
        g = self.gconfig
        if (
            p is None
            or g.probation_slide <= 0.0
            or p.start is None
            or p.start_odom is None
            or self._last_odom is None
        ):
            return
        dead = compose(p.start, compose(invert(p.start_odom), self._last_odom))
        if float(np.hypot(*(est.pose[:2] - dead[:2]))) <= g.probation_slide:
            return
        v_track, v_dead = self.tracker.violations(r, a, [est.pose, dead])
        est.extras["slide_violation"] = v_track - v_dead
        if v_track > v_dead + g.probation_slide_violation:
            est.extras["slide_reset"] = 1.0
            est.pose = dead
            self.tracker.reset(dead, self._last_odom)

    def _probation_evidence(self, r: np.ndarray, a: np.ndarray) -> None:
        """The drive's evidence goes on during a probation (a winner of the evidence rule can
        be held on it, a winner of the single-scan rules is judged on it at the end): this
        scan may become a keyframe, and the kept tracks (the winner at its tracked pose among
        them) are scored on the keyframes they lack, within the search's evidence share of
        the budget."""
        g = self.gconfig
        odom_now = self._last_odom
        if odom_now is None or not g.search_budget_ms:
            return
        self._add_keyframe(r, a, odom_now)
        self.work_ms = self._backfill(odom_now, float(g.search_budget_ms) * g.evidence_share)

    def _probation_search(self, r: np.ndarray, a: np.ndarray) -> None:
        """A search goes on during a single-scan winner's probation
        (``GlobalConfig.probation_searches``) on this scan, seeded by the kept hypotheses,
        with what the budget leaves after the tracker's update and the drive's evidence; a
        finished search's places join the hypotheses (moved by the odometry since its scan)
        and are judged on the drive's keyframes with the winner."""
        g = self.gconfig
        budget = float(g.search_budget_ms or 0.0)
        spent = self.work_ms + hyp_mod.CONFIRM_MS
        if spent >= budget:
            return

        def steps() -> Any:
            P = scan_configuration(r, a, self.config.extraction())
            return search_steps(self.index, r, a, self.config, g, seeds=self._seeds(), P=P)

        spent, res = self._advance_search(spent, budget, steps)
        self.work_ms = spent - hyp_mod.CONFIRM_MS
        if res is not None and self._probation is not None:
            self._probation.searches += 1

    def _drive_holds(self, track: Track, extras: dict[str, float]) -> bool:
        """Whether the drive's keyframes, those made during its probation included, still
        name ``track``: it explains them better than every distinct alternative (a margin
        above 0), within ``drive_max_cost``. A hysteresis: winning took ``drive_margin``;
        keeping a winner through rejected scans takes only that no alternative has caught
        up. Requiring the full margin failed the true place's probation on the tuning log
        fr079 (floor plan, start 4109, 50 ms: held through rejections at a margin of 0.162,
        failed when it dipped to 0.1497, never fixed in 20 m; held, it passes with margins of
        0.11 and more and is fixed at 16.3 m)."""
        if not self._frames or track not in self._tracks:
            return False
        p = self._probation
        rivals = self._tracks
        if p is not None and p.rivals:
            # a place found during the probation has a few keyframes scored yet and can tie
            # the winner there; it is judged on the whole window by the verdict at the end
            # (tuning log fr079 fed every 3rd scan, start 4327: the true place, held through
            # three rejections, failed its probation to places its search had just found)
            ids = {id(r) for r in p.rivals}
            rivals = [t for t in self._tracks if id(t) in ids]
        return self._evidence_won(track, extras, keep=True, tracks=rivals)

    def _refine_verdict(self, p: Probation) -> bool:
        """Advance the verdict's refinement (``GlobalConfig.verdict_refine``,
        :mod:`service.core.window_refine`) with what the scan's budget leaves after the
        tracker's update and the drive's evidence; whether it is done (the winner and its
        closest alternatives then stand where the drive's beams fit each best)."""
        g = self.gconfig
        if p.refine is None:
            p.refine = wr_mod.start(p.track, self._tracks, self._frames, g)
        budget = float(g.search_budget_ms or np.inf)
        spent = self.work_ms + hyp_mod.CONFIRM_MS
        spent, done = wr_mod.advance(p.refine, self.index, self.config, g, spent, budget)
        self.work_ms = spent - hyp_mod.CONFIRM_MS
        return done

    def _probation_step(
        self,
        est: Estimate,
        delta: np.ndarray | None,
        collapsed: bool,
        r: np.ndarray,
        a: np.ndarray,
    ) -> Estimate:
        """One tracked scan of a probation. The odometry ``delta`` moves the kept hypotheses
        and counts towards the travel. The probation fails where tracking would have ended --
        the tracker loses the scan, or ``collapsed``: ``lost_after`` scans in a row rejected
        with a score below ``collapse_score`` -- and on a scan without odometry (no travel
        to count). The search then goes on with the hypotheses it held; the winner stays
        among them, moved by the odometry, and has to win again (it keeps counting as the
        alternative to every other: dropping it let a poor alias win the evidence rule
        unopposed on tuning building 4, after one furnished room's scans failed the true
        place's probation). Passed, the tracker's estimate is the fix.

        A winner of the evidence rule is held through the rejections while the drive's
        evidence, which goes on during the probation (:meth:`_probation_evidence`), still
        names it and the scan does not contradict it (``GlobalConfig.probation_hold_violation``);
        once the rejections have reached the bar, every later scan of the probation must hold
        so. A winner of the single-scan rules fails at the probation's end if a distinct
        alternative then explains the drive's keyframes, those of the probation included,
        better (``GlobalConfig.probation_verdict``); with ``probation_contest_all`` so does a
        winner of the window's mean, and its probation searches as theirs does."""
        p = self._probation
        assert p is not None
        g = self.gconfig
        self.work_ms = 0.0  # this scan's search work (evidence, search, refinement) follows
        rejected = "rejected" in est.extras
        p.rejected += rejected
        drive_won = "drive_rule" in p.extras
        if delta is not None:
            moved = self._move_kept(delta)
            p.left -= moved
            p.relock = 0.0 if rejected else p.relock + moved
            # while the verdict's refinement runs, the keyframes it judges stay as they are
            if (drive_won or g.probation_verdict) and p.refine is None:
                self._probation_evidence(r, a)
            contested = not drive_won or g.probation_contest_all
            if p.searches < g.probation_searches and g.probation_verdict and contested:
                self._probation_search(r, a)
        struck = collapsed or p.rejected >= g.probation_rejects
        if (
            struck
            and delta is not None
            and drive_won
            and g.probation_hold_violation > 0.0
            and self._drive_holds(p.track, est.extras)
            and self.tracker.violations(r, a, [est.pose])[0] <= g.probation_hold_violation
        ):
            struck = False
            est.extras["probation_held"] = 1.0
        failed = struck or est.status == "lost" or delta is None
        # a winner of the newest keyframes is judged at its probation's end as a single-scan
        # winner is: what named it is still in the window, and the probation's keyframes may
        # show it was a stretch where a wrong place fitted better (tuning building 1, start
        # 13: a place 15 m off won on the newest 8 keyframes; 2 m later the true place
        # explained the window better by 0.16, and the probation passed)
        verdict = not drive_won or "drive_recent" in p.extras or g.probation_contest_all
        ended = not failed and p.left <= 0.0
        judged = ended and g.probation_verdict and verdict
        frames = self._frames
        if judged and g.verdict_refine and self._frames:
            if not self._refine_verdict(p):
                est.extras["verdict_refining"] = 1.0
                return self._on_probation(est)
            assert p.refine is not None
            frames = p.refine.frames
        beaten = judged and ev_mod.beaten(
            p.track, self._tracks, frames, g, g.probation_verdict_margin
        )
        # a winner of the window's mean is not judged so (its deciding keyframes slide out
        # during the probation) but fails if the drive has turned: the newest keyframes now
        # name a distinct alternative by the second way's margin, the window not against it
        overturned = (
            ended
            and g.probation_reversal
            and not verdict
            and ev_mod.overturned(p.track, self._tracks, self._frames, g)
        )
        if failed or beaten or overturned:
            self._probation = None
            self._searching = True
            self._history = []
            self._unfit = 0
            self.tracker.reset(None)
            p.track.wins = 0
            extras = {"probation_failed": 1.0, "hypotheses": float(len(self._tracks))}
            if beaten:
                extras["probation_beaten"] = 1.0
            if overturned:
                extras["probation_overturned"] = 1.0
            amb = ambiguity([t.hyp for t in self._tracks], self.gconfig)
            return self._unresolved(self._tracks[0], amb, extras)
        relocking = p.rejected >= g.probation_rejects and p.relock < g.probation_relock
        if p.left > 0.0 or (g.probation_verdict and rejected) or relocking:
            # a probation passes only on a scan the tracker accepted; on a rejected one it
            # goes on (the rejection counts towards probation_rejects) rather than publish
            # a pose the scan did not fit (tuning building 17, start 0, with
            # evidence_short_scale: a place 8.4 m off passed on a rejected scan and was lost
            # on the next). A probation held through the tracker's rejections
            # (probation_hold_violation) passes only once the tracker has accepted the scans
            # again over probation_relock metres: while it rejected them it followed the
            # odometry alone, and one accepted scan does not show it found the place again
            # (tuning log fr079, floor plan, fed every 3rd scan, start 1174: the robot backs
            # up for 3 m while its odometry counts forward; held through 5 rejections, the
            # probation passed on the next accepted scan 1.29 m off)
            return self._on_probation(est)
        self._probation = None
        self._since_fix = 0
        self._tracks = []
        self._history = []
        est.ambiguity = p.ambiguity
        est.extras.update({"global_fix": 1.0, "probation_passed": 1.0, **p.extras})
        return est
