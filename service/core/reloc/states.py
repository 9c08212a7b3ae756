"""Relocalisation as a state machine: the states (:class:`Tracking`, :class:`DeadReckoning`,
:class:`Searching`, :class:`Probation`) as objects and one transition function, :func:`step`
(``(state, scan) -> (state, estimate)``). The transitions are drawn in
docs/architecture-core.md and argued in docs/decisions/0017.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from service.core.pose import compose, invert, mahalanobis2, propagate, sigma_xy
from service.core.reloc import drive as dr
from service.core.reloc import global_search as gs
from service.core.reloc.config import GlobalConfig
from service.core.reloc.decision import CELL_VOLUME, Prior, Verdict, decide
from service.core.reloc.view_index import ViewIndex
from service.core.reloc.view_index.viewpoints import SPACING
from service.core.shapes.configuration import Configuration, scan_configuration
from service.core.tracking.localizer import ShapeConfig, ShapeLocalizer
from service.core.tracking.scan_odometry import OdometryStep
from service.core.types import Estimate, Status, wrap_angle

#: Heading offsets (rad) a kept hypothesis seeds the next search at (a turn the fit misses).
SEED_TURNS = (0.0, -0.4, 0.4, -0.8, 0.8)
#: Work (reference ms) of the tracker's confirmation of a winner: one update from a reset.
CONFIRM_MS = 20.0
#: Least covariance (m², rad²) of a pose the map just confirmed: accepted fits differ from the
#: odometry's step by up to ~5 cm and ~1.5 degrees, more than a fit's own covariance says.
FIX_COV = np.diag([0.05**2, 0.05**2, 0.03**2])
#: Without odometry the prior widens by this times the known speed (m/scan, >= 5 cm) a scan.
HELD_GROWTH = 2.0
#: Budget shares re-scoring the kept hypotheses on the scan and scoring them on the keyframes
#: they lack; the search gets the rest (larger shares for the tracks fixed fewer robots).
RESCORE_SHARE = 0.3
EVIDENCE_SHARE = 0.2
#: A twin check (it searches the map's own view): at most this shortlist and refine_top; under
#: a probation it adds the best this many twins (a plan draws a corridor's look-alikes alike).
TWIN_SHORTLIST = 60
TWIN_REFINE_TOP = 12
TWIN_KEEP = 3
#: The tracker's first fit lies this close to the winner (m, rad) with a sigma of at most this
#: (m): a corridor verifies as well further along; a right fix is pinned to a centimetre.
CONFIRM_DISTANCE = 0.3
CONFIRM_ANGLE = 0.1
CONFIRM_SIGMA = 0.05
#: Sigmas of the dead-reckoned reference a poorly explained fit may stray from it.
GATE_SIGMAS = 3.0
#: A window peak is distinct if places 0.5 m off score <= 1 - this of it (corridor 0-.05, room .4).
DISTINCT_PEAK = 0.3
#: With the odometry prior off, a larger odometry turn (rad) still moves the tracker first.
ODOM_TURN_ASSIST = 1.0


@dataclass(frozen=True)
class Scan:
    """One scan (robot frame) and its odometry step; ``odometry``: the tracker's prior uses it;
    ``from_scans``: laser odometry, which cannot vouch for a pose the scan contradicts."""

    ranges: np.ndarray
    angles: np.ndarray
    odom: OdometryStep
    odometry: bool
    from_scans: bool = False


class Context(Protocol):
    """What the states use of the localiser."""

    config: ShapeConfig
    gconfig: GlobalConfig
    tracker: ShapeLocalizer
    work_ms: float

    @property
    def index(self) -> ViewIndex: ...


@dataclass
class Tracking:
    """The tracker follows. With odometry ``ref`` / ``cov``, carried from the last scan the map
    explained well, gate worse fits (:data:`GATE_SIGMAS`, ``track_sigma``). ``strikes``: scans
    in a row that contradicted the pose; ``broken``: the scan-to-scan fit broke since the last
    well explained scan; ``since_fix``: scans since a search's fix; ``overruled``: the
    wheel-carried prior a fix outside its gate overruled, carried ``doubt_m`` metres more."""

    ref: np.ndarray | None = None
    cov: np.ndarray | None = None
    strikes: int = 0
    since_fix: int = 1 << 30
    broken: bool = False
    name: str = "tracking"
    overruled: Prior | None = None
    doubt_m: float = 0.0


@dataclass
class DeadReckoning:
    """The map does not explain the scans: ``pose`` / ``cov`` dead-reckoned (status ``lost``)
    until ``relock_scans`` (``relock``) the tracker explains well from it, or a search starts
    from it; ``strikes`` and ``broken`` as :class:`Tracking`'s."""

    pose: np.ndarray
    cov: np.ndarray
    relock: int = 0
    strikes: int = 0
    broken: bool = False
    name: str = "dead_reckoning"


@dataclass
class Searching:
    """The search over a ``drive``: ``prior`` where the robot may be (default uniform), the
    ``status`` (``initializing``, ``lost`` after a fix); ``relock`` as :class:`DeadReckoning`'s,
    from the prior's mean (``weak``: one of those fits explained less than ``good_support``)."""

    drive: dr.Drive = field(default_factory=dr.Drive)
    prior: Prior = field(default_factory=lambda: Prior(None, None, 1.0, 1.0))
    status: Status = "initializing"
    relock: int = 0
    name: str = "searching"
    weak: bool = False


@dataclass
class Probation:
    """With odometry a ``winner`` among the ``drive``'s tracks is tracked ``probation_travel``
    m (``left`` to go), then fixed once the decision names it at ``pass_llr`` (``fix_llr`` after
    a loss), failed once not at ``fix_llr``; ``rejected``: contradicting scans in a row."""

    drive: dr.Drive
    prior: Prior
    winner: dr.Track
    left: float
    status: Status = "initializing"
    rejected: int = 0
    ambiguity: float = 1.0
    name: str = "probation"


State = Tracking | DeadReckoning | Searching | Probation


def fit_cov(est: Estimate) -> np.ndarray:
    """The covariance a fix starts the reference with: the fit's, at least :data:`FIX_COV`."""
    if est.covariance is None:
        return FIX_COV.copy()
    c = np.asarray(est.covariance, dtype=np.float64).reshape(3, 3)
    return np.maximum(c, 0.0) * np.eye(3) + FIX_COV if np.all(np.isfinite(c)) else FIX_COV.copy()


def _fit(ctx: Context, scan: Scan) -> Estimate:
    o = scan.odom
    return ctx.tracker.update(scan.ranges, scan.angles, o.reading, o.matched_from, o.spread)


def _contradicts(ctx: Context, scan: Scan, pose: np.ndarray, cov: np.ndarray | None = None) -> bool:
    """Whether more than ``contradiction`` of the beams return from beyond a drawn wall at
    ``pose``, by the tracker's margin plus, with ``cov``, :data:`GATE_SIGMAS` of its sigma."""
    margin = ctx.config.violation_margin
    if cov is not None:
        margin += GATE_SIGMAS * sigma_xy(cov)
    share = ctx.tracker.violations(scan.ranges, scan.angles, [pose], margin)[0]
    return share > ctx.gconfig.contradiction


def step(ctx: Context, state: State, scan: Scan) -> tuple[State, Estimate]:
    """The one transition function: the next state and the estimate to publish."""
    if isinstance(state, Tracking):
        new, est = _tracking(ctx, state, scan)
    elif isinstance(state, DeadReckoning):
        new, est = _dead_reckoning(ctx, state, scan)
    elif isinstance(state, Probation):
        new, est = _probation(ctx, state, scan)
    else:
        new, est = _searching(ctx, state, scan)
    est.state = new.name  # type: ignore[assignment]
    if isinstance(new, Searching) and est.ambiguity is None:
        est.ambiguity = 1.0  # a search that has only begun: no place leads yet
    if not isinstance(new, Tracking) and est.status == "tracking":
        est.status = "lost"
    return new, est


def _tracking(ctx: Context, s: Tracking, scan: Scan) -> tuple[State, Estimate]:
    g = ctx.gconfig
    o = scan.odom
    if o.delta is not None and not scan.odometry and abs(float(o.delta[2])) > ODOM_TURN_ASSIST:
        # a turn the tracker cannot bridge without its odometry prior (a look-around spin)
        ctx.tracker.predict(o.delta)
    est = _fit(ctx, scan)
    if est.ambiguity is not None:
        # the tracker's compares step-2 hypotheses that mostly converge: the search's is published
        est.extras["tracker_ambiguity"] = float(est.ambiguity)
    est.ambiguity = None
    s.since_fix += 1
    rejected = "rejected" in est.extras
    if not scan.odometry:
        s.ref = s.cov = None
        if est.status == "lost" or (rejected and est.score < g.collapse_score):
            # nothing bridges a scan that fits the map nowhere near the pose
            est.extras["collapsed"] = 1.0
            return _lost(ctx, est.pose, None, False), est
        return s, est
    if o.delta is None or s.ref is None or s.cov is None:
        s.ref, s.cov = est.pose.copy(), fit_cov(est)  # the reference starts here
        return s, est
    noise = o.noise(ctx.config.motion)
    s.ref, s.cov = propagate(s.ref, s.cov, o.delta, noise)
    if s.overruled is not None:
        s.doubt_m -= o.step
        s.overruled = s.overruled.moved(o.delta, noise) if s.doubt_m > 0.0 else None
    slid = False
    if scan.from_scans and g.scan_odometry_violation < 1.0:
        # an odometry measured from the scans moves a pose that slid along a corridor, or
        # turned wrong, as precisely as a right one: only beams through the map's walls tell
        share = ctx.tracker.violations(scan.ranges, scan.angles, [est.pose])[0]
        est.extras["pose_violation"] = share
        slid = share > g.scan_odometry_violation
    if not slid and not rejected and (est.explained or 0.0) >= g.good_support:
        s.ref, s.cov, s.strikes, s.broken = est.pose.copy(), fit_cov(est), 0, False
        return s, est
    # a poorly explained scan contradicts the pose after a scan-to-scan break (a kidnap), else
    # if rejected with beams through drawn walls, scoring low unless laser odometry carries it
    low = est.score < g.collapse_score
    s.broken = (s.broken or o.broken) and low
    doubted = low or scan.from_scans
    contradicted = slid or s.broken or (rejected and doubted and _contradicts(ctx, scan, est.pose))
    s.strikes = s.strikes + 1 if contradicted else 0
    if s.strikes >= ctx.config.lost_after:
        est.extras["contradicted"] = 1.0
        return _lost(ctx, s.ref, s.cov, not scan.from_scans, s.overruled), est
    stray = not rejected and mahalanobis2(est.pose, s.ref, s.cov + FIX_COV) > GATE_SIGMAS**2
    if stray or est.status == "lost" or sigma_xy(s.cov) > g.track_sigma:
        est.extras["stray" if stray else "unexplained"] = 1.0
        if s.overruled is not None:  # doubted: the search, not a dead-reckoned look-alike
            return _lost(ctx, s.ref, s.cov, True, s.overruled), est
        ctx.tracker.reset(None)
        dead = DeadReckoning(s.ref.copy(), s.cov.copy(), strikes=s.strikes, broken=s.broken)
        return dead, _dead_estimate(dead, est)
    return s, est


def _lost(
    ctx: Context,
    pose: np.ndarray,
    cov: np.ndarray | None,
    carried: bool,
    doubted: Prior | None = None,
) -> Searching:
    """A search after the track is lost at ``pose`` (``cov``: dead-reckoned, by wheel odometry
    if ``carried``; without odometry the last tracked pose, widened scan by scan): its prior
    the pose's Gaussian with ``kidnap_weight`` spread over the map (a ``doubted`` fix's: the
    prior it overruled, widened to hold the pose), its first track the pose."""
    speed = ctx.tracker.known_speed()
    ctx.tracker.reset(None)
    if cov is None:
        step_m = 0.0 if speed is None else float(np.hypot(*speed))
        grow = (HELD_GROWTH * max(step_m, 0.05)) ** 2
        cov = np.diag([grow, grow, math.pi**2])
    pose = np.asarray(pose, dtype=np.float64).copy()
    held = dr.Track(pose.copy(), gs.Hypothesis(pose=pose.copy(), cost=0.05))
    prior = Prior(pose, cov.copy(), ctx.gconfig.kidnap_weight, 0.0, carried)
    if doubted is not None and doubted.mean is not None and doubted.cov is not None:
        d = np.array([*(pose[:2] - doubted.mean[:2]), wrap_angle(float(pose[2] - doubted.mean[2]))])
        prior = dataclasses.replace(doubted, cov=doubted.cov + np.outer(d, d))
    return Searching(dr.Drive(tracks=[held], speed=speed), prior, "lost")


def _dead_estimate(d: DeadReckoning, est: Estimate) -> Estimate:
    return Estimate(
        pose=d.pose.copy(),
        status="lost",
        score=est.score,
        explained=est.explained,
        covariance=d.cov.copy(),
        extras=est.extras,
    )


def _relock(
    ctx: Context, pose: np.ndarray, cov: np.ndarray, scan: Scan
) -> tuple[Estimate, np.ndarray, np.ndarray, bool]:
    """The tracker run from the dead-reckoned ``pose`` / ``cov``: its fit, the pose (the fit's
    if good) and covariance after this scan, and whether the fit is good: accepted, explaining
    ``good_support``, within :data:`GATE_SIGMAS`. Else it runs from the window search's peak
    over the gate if :data:`DISTINCT_PEAK`, needing ``relock_support``: the odometry drifts past
    the fit's half-metre reach long before the gate, and a distinct peak is the rest."""
    o, g = scan.odom, ctx.gconfig
    assert o.delta is not None
    start, (pose, cov) = pose, propagate(pose, cov, o.delta, o.noise(ctx.config.motion))
    est, good = _relock_fit(ctx, scan, start, pose, cov, g.good_support)
    if not good and g.relock_window:
        half = GATE_SIGMAS * sigma_xy(cov), GATE_SIGMAS * math.sqrt(max(float(cov[2, 2]), 0.0))
        peak = ctx.tracker.window(scan.ranges, scan.angles, pose, *half)
        if peak is not None and peak.distinct >= DISTINCT_PEAK:
            start = compose(peak.pose, invert(o.delta))
            support = min(g.good_support, g.relock_support)
            again, good = _relock_fit(ctx, scan, start, pose, cov, support)
            est = again if good else est  # the tracker's state then is unused: reset next scan
    return est, est.pose.copy() if good else pose, cov, good


def _relock_fit(
    ctx: Context, scan: Scan, start: np.ndarray, pose: np.ndarray, cov: np.ndarray, support: float
) -> tuple[Estimate, bool]:
    ctx.tracker.reset(start, scan.odom.previous)
    est = _fit(ctx, scan)
    est.ambiguity = None
    good = (
        "rejected" not in est.extras
        and est.status == "tracking"
        and (est.explained or 0.0) >= support
        and mahalanobis2(est.pose, pose, cov + FIX_COV) <= GATE_SIGMAS**2
    )
    return est, good


def _dead_reckoning(ctx: Context, d: DeadReckoning, scan: Scan) -> tuple[State, Estimate]:
    g = ctx.gconfig
    o = scan.odom
    if not scan.odometry or o.delta is None or o.previous is None:
        # the odometry stopped: nothing carries the pose any more
        return _lost(ctx, d.pose, d.cov, False), Estimate(d.pose.copy(), "lost", 0.0)
    est, d.pose, d.cov, good = _relock(ctx, d.pose, d.cov, scan)
    d.relock = d.relock + 1 if good else 0
    d.broken = (d.broken or o.broken) and est.score < g.collapse_score  # as in Tracking
    if d.relock >= g.relock_scans:
        est.extras["relocked"] = 1.0
        return Tracking(est.pose.copy(), fit_cov(est)), est
    contradicted = d.broken or _contradicts(ctx, scan, d.pose, d.cov)
    d.strikes = d.strikes + 1 if contradicted else 0
    out = _dead_estimate(d, est)
    if d.strikes >= ctx.config.lost_after or sigma_xy(d.cov) > g.max_dead_reckoning_sigma:
        # a search, the dead-reckoned pose its prior (and still relocked the same way)
        out.extras["contradicted" if d.strikes else "dead_reckoning_expired"] = 1.0
        return _lost(ctx, d.pose, d.cov, not scan.from_scans), out
    return d, out


def search_seeds(ctx: Context, drive: dr.Drive, prior: Prior, scan: Scan) -> list[np.ndarray]:
    """The kept tracks as the next search's seeds, each turned by :data:`SEED_TURNS`, the prior's
    mean (all round without odometry) and, for a wheel-carried prior where relocks use the
    window, its best place over the gate (a map lacking walls leaves the index no viewpoint)."""

    def turned(p: np.ndarray, turns: tuple[float, ...]) -> list[np.ndarray]:
        return [np.array([*p[:2], wrap_angle(p[2] + t)]) for t in turns]

    out = [q for t in drive.tracks for q in turned(t.pose, SEED_TURNS)]
    odometry = scan.odom.reading is not None
    if prior.mean is None:
        return out
    out += turned(prior.mean, SEED_TURNS if odometry else tuple(np.arange(8) * (np.pi / 4)))
    if odometry and prior.carried and ctx.gconfig.relock_window and prior.cov is not None:
        c = prior.cov  # the gate, as a relock's
        half = GATE_SIGMAS * sigma_xy(c), GATE_SIGMAS * math.sqrt(max(float(c[2, 2]), 0.0))
        peak = ctx.tracker.window(scan.ranges, scan.angles, prior.mean, *half)
        out += [] if peak is None else [peak.pose.copy()]
    return out


def _budget(g: GlobalConfig) -> float:
    return math.inf if g.search_budget_ms is None else float(g.search_budget_ms)


def _search_work(
    ctx: Context, drv: dr.Drive, prior: Prior, scan: Scan
) -> tuple[float, int, tuple[np.ndarray, np.ndarray, Configuration]]:
    """One scan's search work within the budget. Returns the work spent, the finished search's
    candidates (-1: none) and the scan it matched (ranges, angles, configuration)."""
    g = ctx.gconfig
    budget = _budget(g)
    o = scan.odom
    rs, as_ = drv.composite(scan.ranges, scan.angles, o.reading)
    P = scan_configuration(rs, as_, ctx.config.extraction())
    frame = drv.observe(scan.ranges, scan.angles, o.reading, g)  # a plain scan's frame
    spent = dr.rescore(
        ctx.index, drv.tracks, rs, as_, P, ctx.config, g, budget * RESCORE_SHARE, frame
    )
    # under a probation places found are judged before the search looks for more (unjudged,
    # each counts as the leader: a final fix keeps that caution, fix_llr was set with it); the
    # evidence's share follows the search, to judge what it found this scan
    evidence = budget * EVIDENCE_SHARE if o.reading is not None else 0.0
    frames = dr.window(drv.frames, g)
    first = g.probation_travel > 0.0 and o.reading is not None
    if first and any(set(dr.judged(frames)) - t.ll.keys() for t in drv.tracks):
        spent += dr.backfill(
            ctx.index, drv.tracks, frames, o.reading, ctx.config, g, budget - spent
        )
    search_limit = budget - evidence if math.isfinite(budget) else budget
    found = -1
    if drv.twin is not None:
        spent, done, twin = gs.advance(drv.twin.steps, spent, search_limit)
        if done:
            job, drv.twin = drv.twin, None
            if job.track is not None:
                job.track.checked = True
            move = dr.odometry_move(job.odom, o.reading)
            drv.tracks = dr.merge(drv.tracks, twin or [], move, TWIN_KEEP)
    if drv.twin is None and spent < search_limit:
        if drv.job is None:
            seeds = search_seeds(ctx, drv, prior, scan)
            steps = gs.search_steps(ctx.index, rs, as_, ctx.config, g, seeds=seeds, P=P)
            drv.job = dr.Job(steps, None if o.reading is None else o.reading.copy(), frame=frame)
        spent, done, res = gs.advance(drv.job.steps, spent, search_limit)
        if done:
            move = dr.odometry_move(drv.job.odom, o.reading)
            searched = drv.job.frame
            live = searched is not None and any(f is searched for f in dr.window(drv.frames, g))
            scored = searched if live else None
            drv.tracks = dr.merge(drv.tracks, res.hypotheses, move, g.keep, scored)
            drv.job = None
            found = res.candidates
    if o.reading is not None:
        spent += dr.backfill(ctx.index, drv.tracks, frames, o.reading, ctx.config, g, evidence)
    return spent, found, (rs, as_, P)


def _decide(ctx: Context, drv: dr.Drive, prior: Prior) -> Verdict:
    g = ctx.gconfig
    frames = dr.window(drv.frames, g)
    if prior.cells <= 0.0:
        prior.cells = max(1.0, len(ctx.index.viewpoints) * SPACING**2 * 2.0 * math.pi / CELL_VOLUME)
    keys = drv.evidence_keys(g)
    verdict = decide(drv.tracks, frames, keys, prior, g)
    drv.tracks = dr.prune(drv.tracks, frames, keys, verdict.leader, g, prior.mean is not None)
    return verdict


def _searching(ctx: Context, s: Searching, scan: Scan) -> tuple[State, Estimate]:
    g = ctx.gconfig
    o = scan.odom
    drv = s.drive
    relocked: Estimate | None = None
    if o.delta is not None:
        drv.move(o.delta, o.step)
        if s.prior.mean is not None and s.prior.cov is not None and scan.odometry:
            # the dead-reckoned pose relocks as in DeadReckoning while the search goes on
            est, mean, cov, good = _relock(ctx, s.prior.mean, s.prior.cov, scan)
            s.prior = dataclasses.replace(s.prior, mean=mean, cov=cov)
            s.relock = s.relock + 1 if good else 0
            weak = (est.explained or 0.0) < g.good_support
            s.weak = good and (weak or (s.weak and s.relock > 1))
            relocked = est if s.relock >= g.relock_scans else None
            if relocked is not None and not s.weak:  # nothing to wait for: no search work
                relocked.extras["relocked"] = 1.0
                return Tracking(relocked.pose.copy(), fit_cov(relocked)), relocked
        else:
            s.prior = s.prior.moved(o.delta, o.noise(ctx.config.motion))
    elif s.prior.mean is not None and s.prior.cov is not None:
        speed = 0.0 if drv.speed is None else float(np.hypot(*drv.speed))
        grow = (HELD_GROWTH * max(0.05, speed)) ** 2
        s.prior = dataclasses.replace(s.prior, cov=s.prior.cov + np.diag([grow, grow, 0.0]))
    spent, found, (rs, as_, P) = _search_work(ctx, drv, s.prior, scan)
    verdict = _decide(ctx, drv, s.prior)
    lead = verdict.leader
    ctx.work_ms = spent
    # a weak relock waits while the search leads elsewhere (carried into a corridor like its own)
    if relocked is not None and not (
        lead is not None and verdict.llr > 0.0 and gs.distinct(lead.pose, relocked.pose)
    ):
        relocked.extras["relocked"] = 1.0
        return Tracking(relocked.pose.copy(), fit_cov(relocked)), relocked
    extras: dict[str, float] = {"llr": max(-99.0, min(verdict.llr, 99.0)), "work_ms": spent}
    extras["llr_unseen"] = max(-99.0, min(verdict.unseen, 99.0))  # for bench.calibrate_llr
    if found >= 0:
        extras["search_done"] = 1.0
    if lead is not None:
        extras["lead_checked"] = float(lead.checked)
        extras["lead_found"] = float(lead.found)
    if lead is not None and not lead.checked and drv.twin is None:
        caps = {"shortlist": TWIN_SHORTLIST, "refine_top": TWIN_REFINE_TOP}
        tg = g.model_copy(update={k: min(getattr(g, k), v) for k, v in caps.items()})
        n = TWIN_KEEP if o.reading is not None and g.probation_travel > 0.0 else 1
        steps = gs.self_similar_steps(ctx.index, lead.hyp, rs, as_, P, ctx.config, tg, n)
        drv.twin = dr.Job(steps, None if o.reading is None else o.reading.copy(), track=lead)
    if lead is not None and verdict.llr >= g.fix_llr and lead.checked:
        ctx.work_ms += CONFIRM_MS
        est = confirm(ctx, drv, lead, scan, s.prior)
        if est is not None:
            est.ambiguity = verdict.ambiguity
            est.extras.update(extras)
            if o.reading is not None and g.probation_travel > 0.0:
                p = Probation(
                    drv, s.prior, lead, g.probation_travel, s.status, ambiguity=verdict.ambiguity
                )
                return p, _probation_estimate(p, est)
            est.extras["global_fix"] = 1.0
            ref = est.pose.copy() if scan.odometry else None
            t = Tracking(ref, fit_cov(est), since_fix=0)
            if outside(s.prior, est.pose):  # a look-alike as likely as a kidnap: doubted
                t.overruled, t.doubt_m = s.prior, g.evidence_span
            return t, est
        extras["confirm_rejected"] = 1.0
    return s, _guess(s, verdict, extras, g.fix_llr, carried=o.delta is not None)


def _guess(
    s: Searching, verdict: Verdict, extras: dict[str, float], fix_llr: float, carried: bool = True
) -> Estimate:
    """The pose published while searching: while an odometry carries the prior, its mean and
    covariance until a fix (a leader short of ``fix_llr`` may yet be overturned); otherwise
    the leader, else the best track by cost, else the prior's mean or the origin (fr079's
    floor plan without odometry, lost scans within 0.5 m: 8 % at the mean, 15 % leader)."""
    drv, lead = s.drive, verdict.leader
    if carried and s.prior.mean is not None and not verdict.llr >= fix_llr:
        lead = None
    elif lead is None and drv.tracks:
        lead = min(drv.tracks, key=lambda t: t.hyp.cost)
    if lead is not None:
        pose, hyp = lead.pose.copy(), lead.hyp
        score = float(np.clip(1.0 - hyp.cost + 0.05, 0.0, 1.0))
        explained = float(hyp.explained)
    else:
        pose = np.zeros(3) if s.prior.mean is None else s.prior.mean.copy()
        score, explained = 0.0, 0.0
    return Estimate(
        pose=pose,
        status=s.status,
        score=score,
        explained=explained,
        ambiguity=verdict.ambiguity,
        covariance=None if s.prior.cov is None or lead is not None else s.prior.cov.copy(),
        extras=extras,
        hypotheses=len(drv.tracks),
        candidates=dr.candidates(drv.tracks, first=lead),
    )


def confirm(
    ctx: Context, drv: dr.Drive, lead: dr.Track, scan: Scan, prior: Prior | None = None
) -> Estimate | None:
    """The tracker's fit from the winner if it accepts the scan within :data:`CONFIRM_DISTANCE`
    / :data:`CONFIRM_ANGLE` / :data:`CONFIRM_SIGMA` of it, else ``None``. Without a probation
    (floor plans have one) the fit must explain ``relock_support`` of the scan, as a relock's,
    and ``good_support`` outside a dead-reckoned ``prior``'s gate (look-alikes, not kidnaps)."""
    g = ctx.gconfig
    need = 0.0 if g.probation_travel > 0.0 else min(g.good_support, g.relock_support)
    need = g.good_support if need and prior is not None and outside(prior, lead.pose) else need
    ctx.tracker.reset(lead.pose, scan.odom.reading)
    if drv.speed is not None:
        ctx.tracker.set_speed(drv.speed)
    est = _fit(ctx, scan)
    holds = (est.explained or 0.0) >= need
    close = (
        np.hypot(*(est.pose[:2] - lead.pose[:2])) <= CONFIRM_DISTANCE
        and abs(float(wrap_angle(est.pose[2] - lead.pose[2]))) <= CONFIRM_ANGLE
        and est.covariance is not None
        and sigma_xy(np.asarray(est.covariance).reshape(3, 3)) <= CONFIRM_SIGMA
    )
    if est.status == "tracking" and "rejected" not in est.extras and close and holds:
        return est
    ctx.tracker.reset(None)
    return None


def outside(prior: Prior, pose: np.ndarray) -> bool:
    """Whether ``pose`` lies outside the :data:`GATE_SIGMAS` gate of a wheel-carried prior."""
    if not prior.carried or prior.mean is None or prior.cov is None:
        return False
    return mahalanobis2(pose, prior.mean, prior.cov + FIX_COV) > GATE_SIGMAS**2


def _probation_estimate(p: Probation, est: Estimate, x: dict[str, float] | None = None) -> Estimate:
    est.extras.update(x or {})
    est.status = p.status
    est.ambiguity = p.ambiguity
    est.extras["probation"] = max(0.0, p.left)
    est.hypotheses = len(p.drive.tracks)
    est.candidates = dr.candidates(p.drive.tracks, first=p.winner)
    return est


def _probation(ctx: Context, p: Probation, scan: Scan) -> tuple[State, Estimate]:
    g = ctx.gconfig
    o = scan.odom
    est = _fit(ctx, scan)
    est.ambiguity = None
    drv = p.drive
    rejected = "rejected" in est.extras
    # as in Tracking, the odometry bridges a rejected scan unless it contradicts the pose (a
    # hall a floor plan draws as its outline: the tracker rejects scan after scan there)
    low = est.score < g.collapse_score
    p.rejected = p.rejected + 1 if rejected and low and _contradicts(ctx, scan, est.pose) else 0
    ctx.work_ms = 0.0
    if o.delta is not None and o.reading is not None:
        drv.move(o.delta, o.step)
        p.prior = p.prior.moved(o.delta, o.noise(ctx.config.motion))
        p.winner.pose = est.pose.copy()
        # the travel counts on motion the scans confirm (a failed scan-to-scan fit: raw odometry)
        p.left = g.probation_travel if o.broken else p.left - o.step
        drv.observe(scan.ranges, scan.angles, o.reading, g)
        frames = dr.window(drv.frames, g)
        evidence = _budget(g) * EVIDENCE_SHARE
        ctx.work_ms = dr.backfill(
            ctx.index, drv.tracks, frames, o.reading, ctx.config, g, evidence, p.winner
        )
    else:
        p.left = math.inf  # no travel to count: the probation cannot end well
    if est.status == "lost" or p.rejected >= ctx.config.lost_after or p.left == math.inf:
        return _fail(ctx, p, {"probation_failed": 1.0})
    if p.left > 0.0 or rejected or not all(f.key in p.winner.ll for f in frames):
        # it passes on an accepted scan once the winner is scored on the whole window
        return p, _probation_estimate(p, est)
    verdict = _decide(ctx, drv, p.prior)
    lead, llr = verdict.leader is p.winner, min(verdict.llr, 99.0)
    need = max(g.fix_llr, g.pass_llr if p.prior.mean is None else 0.0)  # decisions/0029
    if lead and verdict.llr >= need:
        est.ambiguity = verdict.ambiguity
        est.extras.update(global_fix=1.0, probation_passed=1.0, llr=llr)
        return Tracking(est.pose.copy(), fit_cov(est), since_fix=0), est
    judged = {"probation_llr": llr, "probation_lead": float(lead)}  # calibrate_llr's input
    if lead and verdict.llr >= g.fix_llr:  # still the winner, short of the pass: it goes on
        return p, _probation_estimate(p, est, judged)
    return _fail(ctx, p, {"probation_failed": 1.0, **judged})


def _fail(ctx: Context, p: Probation, extras: dict[str, float]) -> tuple[State, Estimate]:
    """A failed probation: the search goes on with its hypotheses, the winner among them."""
    ctx.tracker.reset(None)
    s = Searching(p.drive, p.prior, p.status)
    return s, _guess(s, Verdict(None, -math.inf), extras, ctx.gconfig.fix_llr)
