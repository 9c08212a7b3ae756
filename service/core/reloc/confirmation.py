"""Confirmation of a search's winner, and recovery near the last pose: a mixin of
:class:`~service.core.reloc.global_localization.GlobalShapeLocalizer`.

* :meth:`Confirmation._confirm`: the tracker, reset to the winner, must accept the scan close
  to it before tracking starts (with the drive's prior for a winner of the drive's evidence).
* :meth:`Confirmation._reacquire`: after a loss with odometry, the tracker run from the
  dead-reckoned pose resumes tracking after a few accepted scans.
* :meth:`Confirmation._confirmed` / :meth:`Confirmation._near_track`: the decision's
  confirmation of the best hypothesis, and the hypothesis near where the track was lost.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from service.core import numeric
from service.core.reloc import hypotheses as hyp_mod
from service.core.sensor.pose_scoring import Hypothesis
from service.core.types import Estimate, wrap_angle

if TYPE_CHECKING:
    from service.core.reloc.global_config import GlobalConfig

_Track = hyp_mod.Track


def _position_sigma(est: Estimate) -> float:
    """Largest standard deviation (m) of an estimate's xy covariance (0 without one)."""
    if est.covariance is None:
        return 0.0
    c = np.asarray(est.covariance, dtype=np.float64).reshape(3, 3)[:2, :2]
    if not np.all(np.isfinite(c)):
        return float("inf")
    return float(np.sqrt(max(0.0, float(numeric.eigh_sym2(c)[0][-1]))))


class Confirmation:
    """Mixin of :class:`~service.core.reloc.global_localization.GlobalShapeLocalizer` (see the
    module docstring); the attributes are the localiser's."""

    gconfig: GlobalConfig
    tracker: Any
    _tracks: list[_Track]
    _job: hyp_mod.Job | None
    _twin_job: hyp_mod.Job | None
    _history: list[tuple[np.ndarray, np.ndarray, np.ndarray]]
    _anchor: np.ndarray | None
    _anchor_travel: float
    _episode: int
    _last_odom: np.ndarray | None
    _matched_from: np.ndarray | None
    _speed: np.ndarray | None
    _since_fix: int
    _searching: bool
    _reacquired: int
    work_ms: float
    # and the methods _probation_due, _begin_probation (service.core.reloc.drive_search)

    def _confirm(
        self, best: _Track, r: np.ndarray, a: np.ndarray, amb: float, extras: dict[str, float]
    ) -> Estimate | None:
        """The tracker, reset to the winner with this scan's odometry, must accept this scan
        within ``confirm_distance`` / ``confirm_angle`` of it, with a position standard
        deviation of at most ``confirm_sigma``: then tracking starts (the fix is returned);
        ``None`` otherwise (``extras`` records the refusal). The scan's prior is weak: it
        decides alone. A winner of the drive's evidence it fails is confirmed again under
        the odometry's per-scan prior, unless the scan explained itself clearly better
        elsewhere; that place then joins the hypotheses (``GlobalConfig.confirm_drive_prior``)."""
        g = self.gconfig
        free, ok = self._confirm_fit(best, r, a, None)
        est = free if ok else None
        if est is None and g.confirm_drive_prior and "drive_rule" in extras:
            est = self._confirm_held(best, r, a, free, extras)
        if est is None:
            self.tracker.reset(None)
            extras["confirm_rejected"] = 1.0
            return None
        self._since_fix = 0
        self._searching = False
        if self._probation_due(extras):
            return self._begin_probation(best, est, amb, extras)
        self._tracks = []
        self._job = None
        self._twin_job = None
        est.ambiguity = amb
        est.extras.update({"global_fix": 1.0, **extras})
        return est

    def _confirm_held(
        self,
        best: _Track,
        r: np.ndarray,
        a: np.ndarray,
        free: Estimate,
        extras: dict[str, float],
    ) -> Estimate | None:
        """A winner of the drive's evidence whose scan, fitted alone (``free``), failed the
        confirmation: the scan again under the odometry's per-scan prior at the winner
        (``GlobalConfig.confirm_drive_prior``). Unless the fit alone, with the tracker's
        ``min_support``, explained the scan clearly better than the held fit
        (``confirm_unexplained``): the place it pointed to then joins the hypotheses, for
        the drive's evidence to judge, and nothing is confirmed on this scan."""
        g = self.gconfig
        place = self.tracker.last_fit
        free_support = float(free.extras.get("support", 0.0))
        mc = self.tracker.config.motion
        self.work_ms += hyp_mod.CONFIRM_MS
        held, ok = self._confirm_fit(best, r, a, (mc.sigma_xy_floor, mc.sigma_theta_floor))
        if not ok:
            return None
        held_support = float(held.extras.get("support", 0.0))
        if (
            place is None
            or free_support < self.tracker.config.min_support
            or 1.0 - free_support > g.confirm_unexplained * (1.0 - held_support)
        ):
            extras["confirm_held"] = 1.0
            return held
        # the scan contradicts the winner's pose: the drive, not this scan alone nor the
        # winner's prior, must tell the two places apart
        hyp = Hypothesis(pose=place.copy(), cost=best.hyp.cost)
        self._tracks = hyp_mod.merge(self._tracks, [hyp], None, 1)
        extras["confirm_elsewhere"] = 1.0
        return None

    def _confirm_fit(
        self,
        best: _Track,
        r: np.ndarray,
        a: np.ndarray,
        known: tuple[float, float] | None,
    ) -> tuple[Estimate, bool]:
        """The tracker's fit of this scan from the winner (``known``: the prior's sigmas,
        :meth:`ShapeLocalizer.reset`), and whether it passes the confirmation's bars."""
        g = self.gconfig
        # the tracker starts at the fix with this scan's odometry, so the next scan's
        # increment (e.g. the rest of a look-around turn) is its motion prior
        self.tracker.reset(best.pose, self._last_odom, known=known)
        if self._speed is not None:
            self.tracker.set_speed(self._speed)
        est = self.tracker.update(r, a, self._last_odom)
        close = (
            np.hypot(*(est.pose[:2] - best.pose[:2])) <= g.confirm_distance
            and abs(float(wrap_angle(est.pose[2] - best.pose[2]))) <= g.confirm_angle
            and _position_sigma(est) <= g.confirm_sigma
        )
        return est, bool(est.status == "tracking" and "rejected" not in est.extras and close)

    def _reacquire(
        self,
        r: np.ndarray,
        a: np.ndarray,
        start: np.ndarray,
        prev_odom: np.ndarray | None,
        odom: np.ndarray | None,
    ) -> Estimate | None:
        """Run the tracker from ``start``, the dead-reckoned pose of the previous scan, with
        this scan's odometry increment as its motion prior. Returns the estimate that
        resumes tracking after ``reacquire_scans`` accepted scans in a row with support
        ``>= reacquire_support``; ``None`` meanwhile (the anchor follows the accepted fits)."""
        g = self.gconfig
        self.tracker.reset(start, prev_odom)
        est = self.tracker.update(r, a, odom, self._matched_from)
        good = (
            est.status == "tracking"
            and "rejected" not in est.extras
            and (est.explained or 0.0) >= g.reacquire_support
        )
        self._reacquired = self._reacquired + 1 if good else 0
        if not good:
            self.tracker.reset(None)
            return None
        if self._reacquired < g.reacquire_scans:
            # follow the fit; the odometry increment is applied from here on the next scan
            self._anchor = est.pose.copy()
            self.tracker.reset(None)
            return None
        self._searching = False
        self._since_fix = 0
        self._tracks = []
        self._history = []
        self._reacquired = 0
        est.ambiguity = None
        est.extras["reacquired"] = 1.0
        return est

    def _near_radius(self, odometry: bool) -> float:
        g = self.gconfig
        if odometry:
            return g.near_radius + g.near_growth * self._anchor_travel
        speed = float(np.hypot(*self.tracker.motion.velocity.velocity))
        return g.near_radius + 2.0 * speed * self._episode

    def _confirmed(self, best: _Track, amb: float, fused: bool, far: bool, seen: int) -> bool:
        """The decision's confirmation of the best hypothesis (``seen``: the scans it was
        scored on): best on two consecutive scans and seen on every scan of the window (a
        hypothesis that just appeared may be a twin the true one briefly lost to), or clear
        enough on one scan -- which on a composite also needs the plain (not the composite)
        cost bar: a lone mediocre fit far ahead of the rest can mean the true place was not
        found at all. Far from where the track was lost (``far``) the fix moves the estimate
        across the building: it must win scan after scan first."""
        g = self.gconfig
        if far:
            return best.wins >= g.far_confirm_scans
        if best.wins >= 2 and (fused or seen >= min(self._episode, g.window)):
            return True
        if fused:
            return amb < g.fused_single_ambiguity and best.hyp.cost <= g.max_fix_cost
        return amb < g.single_scan_ambiguity

    def _near_track(self, tracks: list[_Track], odometry: bool) -> _Track | None:
        """The best hypothesis near the dead-reckoned last pose, if its cost is within
        ``near_cost_margin`` of the best overall; ``None`` otherwise (or before any loss)."""
        if self._anchor is None or not tracks:
            return None
        g = self.gconfig
        radius = self._near_radius(odometry)
        for t in tracks:  # sorted by cost
            if t.hyp.cost > tracks[0].hyp.cost + g.near_cost_margin:
                return None
            if np.hypot(*(t.pose[:2] - self._anchor[:2])) > radius:
                continue
            if odometry and abs(float(wrap_angle(t.pose[2] - self._anchor[2]))) > g.near_turn:
                continue
            return t
        return None
