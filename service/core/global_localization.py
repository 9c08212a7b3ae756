"""Global localisation (no initial pose, kidnapped robot) and an integrity signal for SBL.

The method in four parts: 1-2 in :mod:`service.core.view_index`, 3 in
:mod:`service.core.global_search`, 4 here; :class:`GlobalConfig` is in
:mod:`service.core.global_config`. This module re-exports their public names.

The shape-based tracker (:class:`service.core.localizer.ShapeLocalizer`) needs a prior pose:
it compares the scan's configuration with the map's abstract sensor reading *from that pose*.
Without a prior, this module compares the scan with abstract sensor readings from everywhere:

1. :func:`candidate_viewpoints` — a grid over the map's free space. A polyline-only map has no
   notion of "inside", so a grid point is kept when a 360-degree virtual scan from it is
   *enclosed* (hits in nearly every direction), it keeps a clearance from every polyline, and
   it does not lie inside a small closed ring (furniture).
2. :class:`ViewIndex` — per viewpoint the map view (:func:`service.core.configuration.map_view`,
   the same extraction as for scans) reduced to its *units* (each feature and each pair of
   consecutive features, as step 1 of §5.3 uses them) with their shape complexity and range
   from the viewpoint, plus a distance field of the map for fast support tests. Built once per
   map (:func:`build_index`) and cached on disk (:func:`load_or_build_index`), keyed by a hash
   of the map content, the extraction parameters and :data:`FORMAT_VERSION`.
3. :func:`global_search` — the §5.3 step-1 idea applied to every viewpoint: the scan's most
   complex units are compared by S* with the view units at a compatible range; every similar
   pair induces an alignment (:func:`service.core.matching.induced_alignment`), i.e. a pose
   hypothesis. Hypotheses are ranked by support (distance field), refined by a point-to-line
   fit (:func:`service.core.pose_batch.fit_pairs`) and verified beam by beam against the map
   (returns where the map predicts them, no beam passing through a map wall). The result is a
   ranked list of distinct hypotheses with an ambiguity in [0, 1] (1 = tie).
4. :class:`GlobalShapeLocalizer` — the :class:`~service.core.types.Localizer` the factory
   returns for ``shape``: tracks with a :class:`ShapeLocalizer`; with no pose, or once the
   tracker's quality collapses (status ``lost``), runs the global search on every scan, keeps
   the best hypotheses across scans and declares a winner only when it is clearly better than
   the best distinct alternative and the tracker confirms it on the same scan. While the
   hypotheses stay ambiguous it publishes ``initializing`` (or ``lost``) with the ambiguity and
   the best guess, never ``tracking``.

Frames and units: REP 103, metres and radians; poses ``[x, y, theta]`` in the map frame; scan
points in the robot frame (x forward, y left).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.core import _kernels, evidence
from service.core import hypotheses as hyp_mod
from service.core.composite import composite_scan
from service.core.configuration import (
    scan_configuration,
)
from service.core.confirmation import Confirmation
from service.core.drive_search import DriveSearch
from service.core.global_config import GlobalConfig
from service.core.global_search import (
    SearchResult,
    _near,
    ambiguity,
    global_search,
    self_similar,
)
from service.core.localizer import ShapeConfig, ShapeLocalizer
from service.core.motion import check_pose3
from service.core.pose import compose, invert
from service.core.pose_scoring import Hypothesis, _field_scores, verify
from service.core.probation import Probation
from service.core.scan_odometry import ScanOdometry
from service.core.types import Estimate, MapData, Status, check_scan, wrap_angle
from service.core.view_index import (
    FORMAT_VERSION,
    ViewIndex,
    build_index,
    cache_path,
    candidate_viewpoints,
    clear_memory_cache,
    index_key,
    load_index,
    load_or_build_index,
    save_index,
)
from service.errors import LocalizationError

__all__ = [
    "FORMAT_VERSION",
    "GlobalConfig",
    "GlobalShapeLocalizer",
    "Hypothesis",
    "LocalizationError",
    "SearchResult",
    "ShapeConfig",
    "ViewIndex",
    "_field_scores",
    "_kernels",
    "ambiguity",
    "build_index",
    "cache_path",
    "candidate_viewpoints",
    "clear_memory_cache",
    "global_search",
    "index_key",
    "load_index",
    "load_or_build_index",
    "save_index",
    "scan_configuration",
    "self_similar",
    "verify",
]


# --------------------------------------------------------------------------------------------
# The localiser: tracking, global search, integrity
# --------------------------------------------------------------------------------------------


#: Heading offsets (rad) under which a kept hypothesis seeds the next scan's search.
_SEED_TURNS = (0.0, -0.4, 0.4, -0.8, 0.8)
_ASSOCIATE = hyp_mod.ASSOCIATE
_Track = hyp_mod.Track


class GlobalShapeLocalizer(Confirmation, DriveSearch):
    """Shape-based localisation with global search (implements
    :class:`service.core.types.Localizer`, method ``shape``).

    ``map_data`` the map; ``initial_pose`` ``[x, y, theta]`` map frame, or ``None`` (unknown:
    global localisation); ``config`` the tracker's :class:`ShapeConfig` (default per map
    kind); ``gconfig`` a :class:`GlobalConfig`; ``cache_dir`` where the map's
    :class:`ViewIndex` is cached (``None``: built in memory). The index is built on the first
    scan that needs a global search, not before.

    Modes: *tracking* — every scan goes to the wrapped :class:`ShapeLocalizer`; its estimate is
    published, except that a rejected scan whose score is below ``gconfig.collapse_score``
    (the scan's shapes no longer fit the map at all) or the tracker's own ``lost`` (after
    ``lost_after`` rejections) switches to *searching* at once and publishes ``lost``.
    The published ``ambiguity`` is the global search's (best vs best distinct hypothesis);
    while tracking it is ``None`` (the tracker's own value is in ``extras``).
    *searching* — every scan runs :func:`global_search`, seeded with the hypotheses kept from
    the previous scans (and, after a loss, the last tracked pose); each hypothesis' cost is
    averaged over the last ``gconfig.window`` scans. The best one wins when its mean cost is
    below ``gconfig.max_fix_cost``, its ambiguity against the best distinct alternative is
    below ``gconfig.max_fix_ambiguity``, it has been best on two consecutive scans and seen on
    every scan of the window (or is best on one with ambiguity below
    ``gconfig.single_scan_ambiguity``), the scan holds enough shape
    (``gconfig.min_information``), and the tracker, reset to it, accepts the same scan within
    ``gconfig.confirm_distance``. Until then the estimate is the
    best guess with status ``initializing`` (never had a fix) or ``lost`` (lost it) and the
    ambiguity; a confident ``tracking`` is only published after a win.
    """

    method = "shape"

    def __init__(
        self,
        map_data: MapData,
        initial_pose: np.ndarray | None,
        config: ShapeConfig | None = None,
        *,
        gconfig: GlobalConfig | None = None,
        cache_dir: Path | None = None,
    ) -> None:
        if config is not None and not isinstance(config, ShapeConfig):
            raise LocalizationError(f"config must be a ShapeConfig, got {type(config).__name__}")
        self.map_data = map_data
        self.config = config or ShapeConfig.for_kind(map_data.kind)
        self.gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.tracker = ShapeLocalizer(map_data, initial_pose, self.config)
        self._scan_odometry = ScanOdometry(self.config.motion.scan_odometry, self.config.motion)
        #: the reading this scan's corrected increment was scan-matched from (or ``None``)
        self._matched_from: np.ndarray | None = None
        self._index: ViewIndex | None = None
        self._tracks: list[_Track] = []
        self._searching = False
        self._search_status: Status = "initializing"
        self._episode = 0
        self._last_odom: np.ndarray | None = None
        #: Scans of the current search, ``(ranges, angles, odometry pose)``, oldest first.
        self._history: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        #: Scans that ran a global search since the last reset (for tests and benchmarks).
        self.searches = 0
        self.reset(initial_pose)

    def __getstate__(self) -> dict[str, object]:
        """Picklable state (a robot moved to another worker process): the view index is
        left out (the new process loads it from its cache on first use) and so is a search
        in progress (a generator; the search starts again on the next scan)."""
        state = dict(self.__dict__)
        state["_index"] = None
        state["_job"] = None
        state["_twin_job"] = None
        state["_confirm_next"] = False
        return state

    @property
    def index(self) -> ViewIndex:
        """The map's view index (loaded or built on first use)."""
        if self._index is None:
            self._index = load_or_build_index(
                self.map_data, self.config, self.gconfig, self.cache_dir
            )
        return self._index

    @property
    def pose(self) -> np.ndarray | None:
        """Last tracked pose (map frame), ``None`` while searching without a fix."""
        return None if self._searching or self._probation is not None else self.tracker.pose

    @property
    def unsettled(self) -> bool:
        """Searching, or fixed by a search fewer than ``gconfig.settle_scans`` scans ago: where
        a service keeps the robot on its search worker (a wrong or early fix that is lost again
        then costs no tracking worker a search)."""
        return (
            self._searching
            or self._probation is not None
            or self._since_fix < self.gconfig.settle_scans
        )

    def set_search_budget(self, ms: float) -> None:
        """Set the per-scan work budget of a budgeted search (``GlobalConfig.
        search_budget_ms``; a search without a budget stays whole). The service halves it
        while other robots share this robot's worker."""
        g = self.gconfig
        if g.search_budget_ms is not None and g.search_budget_ms != ms:
            self.gconfig = g.model_copy(update={"search_budget_ms": float(ms)})

    @property
    def searching(self) -> bool:
        """``True`` while the pose is unknown: a global search on every scan, or its winner
        on probation (``GlobalConfig.probation_travel``)."""
        return self._searching or self._probation is not None

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Forget the history; ``None`` starts a global search (status ``initializing``).
        ``odom``: odometry pose at ``initial_pose`` (the next increment starts from it)."""
        self.tracker.reset(initial_pose, odom)
        self._scan_odometry.reset(None if odom is None else check_pose3(odom, "odom"))
        self._tracks = []
        self._history = []
        self._last_odom = (
            None if initial_pose is None or odom is None else check_pose3(odom, "odom")
        )
        self._searching = initial_pose is None
        self._probation: Probation | None = None  # a winner tracked before it is published
        self._since_fix = self.gconfig.settle_scans  # a given pose needs no settling
        self._search_status = "initializing"
        self._unfit = 0  # consecutive tracked scans that did not fit the map at all
        self._broken = False  # the scan-to-scan fit failed since the map explained a scan
        self._episode = 0
        self._anchor: np.ndarray | None = None  # dead-reckoned last tracked pose after a loss
        self._anchor_travel = 0.0
        self._reacquired = 0  # scans in a row the tracker accepted from the anchor
        self._speed: np.ndarray | None = None  # the tracker's known speed before the loss
        self._job: hyp_mod.Job | None = None  # budgeted search in progress
        self._twin_job: hyp_mod.Job | None = None  # budgeted self-similarity check
        self._rule_refine = None  # budgeted: a refinement before the evidence rule's verdict
        self._confirm_next = False  # budgeted: the tracker confirms a winner on the next scan
        self._search_turn = False  # budgeted: a pending search's turn before a twin check's
        self._travel = 0.0  # odometry travel (m) since the search started
        self._frames: list[evidence.Keyframe] = []  # budgeted: the drive's keyframes
        self._frame_key = 0
        self._candidates = 0  # poses the last finished search induced
        #: reference ms of search work spent on the last scan (budgeted search; benchmarks)
        self.work_ms = 0.0

    def update(
        self,
        ranges: np.ndarray,
        angles: np.ndarray,
        odom: np.ndarray | None = None,
        odom_spread: np.ndarray | None = None,
        from_scans: bool = False,
    ) -> Estimate:
        """Localise one scan (see the class docstring). ``ranges`` metres (NaN = no return),
        ``angles`` radians robot frame, ``odom`` optional odometry pose (own frame; only used
        to move the kept hypotheses between scans; corrected by the scans first,
        ``ShapeConfig.motion.scan_odometry``); ``odom_spread`` its increment's translation
        variance beyond the odometry model's (the tracker's prior,
        :meth:`service.core.motion.MotionModel.predict`); ``from_scans``: ``odom`` was measured
        from the scans themselves (:mod:`service.core.laser_odometry`), so it cannot vouch
        for a pose the scan contradicts, accepted or not."""
        r, a = check_scan(ranges, angles)
        odom = self._corrected_odom(r, a, odom)
        if not self._searching:
            if self._scan_odometry.explained < self.config.motion.scan_odometry.min_inliers:
                self._broken = True  # (NaN: no scan-to-scan fit on this scan, no news)
            self._since_fix += 1
            delta = self._remember_odom(odom)
            if (
                delta is not None
                and not self.tracker.config.motion.use_odometry
                and abs(float(delta[2])) > self.gconfig.odom_turn_assist
            ):
                # a turn the shape tracker cannot bridge (e.g. a look-around spin that goes on
                # after the fix): trust the odometry's heading change for the prior
                self.tracker.predict(delta)
            est = self.tracker.update(r, a, odom, self._matched_from, odom_spread)
            # The tracker's own ambiguity compares its step-2 hypotheses, which often converge
            # to the same pose (a "tie" of one pose with itself): not an integrity signal.
            # It stays in extras; the published ambiguity is the global one (None here).
            if est.ambiguity is not None:
                est.extras["tracker_ambiguity"] = float(est.ambiguity)
            est.ambiguity = None
            rejected = "rejected" in est.extras
            # scans that no longer fit the map at all collapse the track: one such scan
            # without an odometry prior, ``lost_after`` in a row with one (a furnished room on
            # a floor plan, or a crowd, can leave a scan unexplained while odometry holds)
            odometry_prior = odom is not None and self.tracker.config.motion.use_odometry
            low = est.score < self.gconfig.collapse_score
            unfit = rejected and low
            if odometry_prior and self._probation is None and self.gconfig.collapse_violation >= 0:
                # bridged by the odometry unless the scan contradicts the pose; after a break
                # in the laser's view even an accepted scan must fit (the tracker accepts a
                # kidnapped scan that a floor plan's outline happens to half explain)
                unfit = low and (self._broken or (rejected and self._contradicted(r, a, est)))
                if from_scans and not unfit and self.gconfig.scan_odometry_violation < 1.0:
                    # An odometry measured from the scans moves a pose that slid along a
                    # corridor (where neither the scans nor a floor plan pin it), or turned
                    # wrong, as precisely as a right one: the map alone can tell, and beams
                    # through its walls do.
                    share = self.tracker.violations(r, a, [est.pose])[0]
                    est.extras["pose_violation"] = share
                    unfit = share > self.gconfig.scan_odometry_violation
            if not low:
                self._broken = False  # the map explains the scan again
            self._unfit = self._unfit + 1 if unfit else 0
            need = self.tracker.config.lost_after if odometry_prior else 1
            collapsed = self._unfit >= need
            if self._probation is not None:
                # the probation fails where tracking would have collapsed
                self._slide_check(r, a, est)
                return self._probation_step(est, delta, collapsed, r, a)
            if est.status == "lost" or collapsed:
                speed = self.tracker.known_speed()
                self._start_search(est.pose)
                self._speed = speed
                est.status = "lost"
                est.ambiguity = 1.0  # no hypotheses yet: nothing tells the places apart
            return est
        return self._search(r, a, odom)

    # ---------------------------------------------------------------- internals
    #: The scan-to-scan fit failed to match a scan to the one before since the map last
    #: explained a tracked scan (:meth:`_contradicted`); a class default, so a state pickled
    #: before it existed loads.
    _broken: bool = False

    def _contradicted(self, r: np.ndarray, a: np.ndarray, est: Estimate) -> bool:
        """Whether a rejected scan that does not fit the map contradicts the tracked pose:
        more than ``GlobalConfig.collapse_violation`` of the tracker's violation beams return
        from beyond a mapped wall. ``False``: the odometry bridges it (``extras['bridged']``)."""
        g = self.gconfig
        share = self.tracker.violations(r, a, [est.pose])[0]
        est.extras["pose_violation"] = share
        if share > g.collapse_violation:
            return True
        est.extras["bridged"] = 1.0
        return False

    def _corrected_odom(
        self, r: np.ndarray, a: np.ndarray, odom: np.ndarray | None
    ) -> np.ndarray | None:
        """The scan's odometry pose corrected by matching the scan to the previous one
        (:class:`service.core.scan_odometry.ScanOdometry`), or as received when that is off;
        a scan without odometry makes the next reading start afresh."""
        self._matched_from = None
        if odom is None:
            self._scan_odometry.reset(None)
            return None
        o = check_pose3(odom, "odom")
        if not self.config.motion.scan_odometry.enabled:
            return o
        out = self._scan_odometry.correct(r, a, o)
        self._matched_from = self._scan_odometry.matched_from
        return out

    def _remember_odom(self, odom: np.ndarray | None) -> np.ndarray | None:
        """Odometry delta since the previous scan (robot frame) or ``None``."""
        if odom is None:
            self._last_odom = None
            return None
        o = np.asarray(odom, dtype=np.float64)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise LocalizationError(f"odom: expected 3 finite values, got {o.shape}")
        delta = None if self._last_odom is None else compose(invert(self._last_odom), o)
        self._last_odom = o
        return delta

    def _composite(self, r: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The scan the search matches: this one alone, or, when this scan and earlier ones of
        the search came with odometry, the virtual 360-degree composite of the last
        ``gconfig.composite_scans`` of them (:func:`service.core.composite.composite_scan`)
        taken within ``gconfig.composite_travel`` of this pose."""
        g = self.gconfig
        if self._last_odom is None or g.composite_scans <= 1:
            self._history = []
            return r, a
        here = self._last_odom
        self._history = [
            h
            for h in self._history[-(g.composite_scans - 1) :]
            if np.hypot(*(h[2][:2] - here[:2])) <= g.composite_travel
        ]
        self._history.append((r, a, here.copy()))
        if len(self._history) == 1:
            return r, a
        # bins no finer than the laser's beams (a coarser laser would leave holes that split
        # every polyline)
        inc = float(np.median(np.abs(np.diff(a)))) if a.size > 1 else 0.0
        bins = g.composite_bins
        if inc > 0.0:
            bins = int(min(bins, max(8, np.floor(2.0 * np.pi / inc + 1e-6))))
        return composite_scan(self._history, bins)

    def _seeds(self) -> list[np.ndarray]:
        """The kept hypotheses as seeds of this scan's search, each also turned by +-0.4 and
        +-0.8 rad: a robot may turn that much between two scans, more than the fit recovers."""
        out = []
        for t in self._tracks:
            for dth in _SEED_TURNS:
                out.append(np.array([t.pose[0], t.pose[1], wrap_angle(t.pose[2] + dth)]))
        return out

    def _start_search(self, last_pose: np.ndarray | None) -> None:
        self._searching = True
        self._probation = None
        self._unfit = 0
        self._broken = False
        self._search_status = "lost"
        self._episode = 0
        self._tracks = []
        self._history = []
        self._anchor = None
        self._anchor_travel = 0.0
        self._reacquired = 0
        self._job = None
        self._twin_job = None
        self._rule_refine = None
        self._confirm_next = False
        self._search_turn = False
        self._travel = 0.0
        self._frames = []
        if last_pose is not None:
            p = np.asarray(last_pose, dtype=np.float64).copy()
            self._anchor = p.copy()
            # the last tracked pose was verified by the tracker a scan ago: it enters with that
            # history, so a transient loss (an occlusion) recovers to it first
            floor = self.gconfig.cost_floor
            self._tracks = [_Track(p, [floor], Hypothesis(pose=p, cost=floor))]

    def _search(self, r: np.ndarray, a: np.ndarray, odom: np.ndarray | None) -> Estimate:
        g = self.gconfig
        self.searches += 1
        self._episode += 1
        prev_odom = self._last_odom
        delta = self._remember_odom(odom)
        if delta is not None:
            start = self._anchor
            self._move_kept(delta)
            if start is not None:
                # (with odometry only: without it the held anchor is no motion prior the
                # tracker could be trusted from; tuning seeds 11 and 16 tracked wrong places)
                back = self._reacquire(r, a, start, prev_odom, odom)
                if back is not None:
                    return back
        rs, as_ = self._composite(r, a)
        P = scan_configuration(rs, as_, self.config.extraction())
        if g.search_budget_ms is not None:
            return self._search_budgeted(r, a, rs, as_, P, delta is not None)
        seeds = self._seeds() + self._anchor_seeds(delta is not None)
        res = global_search(self.index, rs, as_, self.config, g, seeds=seeds, P=P)
        # associate this scan's hypotheses with the tracks
        new_tracks: list[_Track] = []
        for h in res.hypotheses[: g.keep]:
            prev = next((t for t in self._tracks if _near(t.pose, h.pose, *_ASSOCIATE)), None)
            costs = (prev.costs if prev is not None else []) + [h.cost]
            wins = prev.wins if prev is not None else 0
            if any(_near(t.pose, h.pose, *_ASSOCIATE) for t in new_tracks):
                continue
            new_tracks.append(_Track(h.pose.copy(), costs[-g.window :], h, wins))
        # mean cost over the window; a hypothesis seen on fewer of this search's scans pays
        # 1.0 for each scan it was missing from
        n = min(self._episode, g.window)
        fused = len(self._history) > 1
        for t in new_tracks:
            if fused:
                # the composite already holds the earlier scans: its cost is the evidence
                # (a mean over the window would count them twice and punish a hypothesis
                # that only the wider view revealed)
                continue
            missing = max(0, n - len(t.costs))
            t.hyp.cost = (sum(t.costs) + missing) / (len(t.costs) + missing)
        new_tracks.sort(key=lambda t: t.hyp.cost)
        for k, t in enumerate(new_tracks):
            t.wins = t.wins + 1 if k == 0 else 0
        self._tracks = new_tracks
        amb = ambiguity([t.hyp for t in new_tracks], g)
        if not new_tracks:
            return self._no_hypothesis({"hypotheses": 0.0, "candidates": float(res.candidates)})
        best = new_tracks[0]
        near_track = self._near_track(new_tracks, delta is not None)
        if near_track is not None:
            best = near_track
        far = self._anchor is not None and near_track is None
        extras = {
            "hypotheses": float(len(new_tracks)),
            "candidates": float(res.candidates),
            "search_cost": best.hyp.cost,
            "hit": best.hyp.hit,
            "violation": best.hyp.violation,
            "information": res.information,
        }
        confirmed = self._confirmed(best, amb, fused, far, len(best.costs))
        informative = res.information >= g.min_information
        max_amb = g.fused_fix_ambiguity if fused else g.max_fix_ambiguity
        fix_cost = g.fused_fix_cost if fused else g.max_fix_cost
        if near_track is not None:
            # recovered near the lost track: the motion history rules out the far twins, but
            # the fit itself must be as good as a single scan's fix (the dead-reckoned pose is
            # published meanwhile, and is better than a mediocre fit next to it)
            confirmed, informative, amb = True, True, 0.0
            fix_cost = g.max_fix_cost
            extras["near_track"] = 1.0
        if best.hyp.cost <= fix_cost and amb <= max_amb and confirmed and informative:
            twin = None
            if near_track is None:
                twin = self_similar(self.index, best.hyp, rs, as_, P, self.config, g)
            if twin is not None:
                twin_amb = ambiguity([best.hyp, twin], g)
                extras["twin_ambiguity"] = twin_amb
                if twin_amb > max_amb:
                    # the map looks alike at another place and the scan cannot tell them apart:
                    # keep both as tracks and wait for evidence
                    self._tracks.append(_Track(twin.pose.copy(), [twin.cost], twin))
                    amb = max(amb, twin_amb)
                    extras["twin_rejected"] = 1.0
                    return self._unresolved(best, amb, extras)
            est = self._confirm(best, r, a, amb, extras)
            if est is not None:
                return est
        if far and self._anchor is not None and best.wins < g.far_confirm_scans:
            # the best guess to publish is still the dead-reckoned track, not a far place
            # that has not yet proven itself
            guess = _Track(self._anchor.copy(), best.costs, best.hyp, best.wins)
            return self._unresolved(guess, amb, extras)
        return self._unresolved(best, amb, extras)

    def _no_hypothesis(self, extras: dict[str, float]) -> Estimate:
        """The estimate while no hypothesis is known (yet): the dead-reckoned last pose after
        a loss, else the origin; ambiguity 1."""
        return Estimate(
            pose=np.zeros(3) if self._anchor is None else self._anchor.copy(),
            status=self._search_status,
            score=0.0,
            explained=0.0,
            ambiguity=1.0,
            extras=extras,
            hypotheses=len(self._tracks),
            candidates=hyp_mod.candidates(self._tracks),
        )

    def _anchor_seeds(self, odometry: bool) -> list[np.ndarray]:
        """The dead-reckoned last pose as seeds: turned by the usual offsets with odometry,
        all round the circle without (the heading may have turned any amount)."""
        if self._anchor is None:
            return []
        turns = _SEED_TURNS if odometry else tuple(np.arange(8) * (np.pi / 4))
        x, y, th = self._anchor
        return [np.array([x, y, wrap_angle(th + t)]) for t in turns]

    def _unresolved(self, best: _Track, amb: float, extras: dict[str, float]) -> Estimate:
        """The best guess while the search goes on (status ``initializing`` or ``lost``)."""
        g = self.gconfig
        score = float(np.clip(1.0 - best.hyp.cost + g.cost_floor, 0.0, 1.0))
        return Estimate(
            pose=best.pose.copy(),
            status=self._search_status,
            score=score,
            explained=float(best.hyp.explained),
            ambiguity=float(amb),
            extras=extras,
            hypotheses=len(self._tracks),
            candidates=hyp_mod.candidates(self._tracks),
        )
