"""Shape-based localisation (SBL, paper §4-§6): :class:`ShapeLocalizer` (its configuration,
:class:`~service.core.tracking.shape_config.ShapeConfig`, is re-exported here).

What runs where, per scan (:meth:`ShapeLocalizer.update`; docs/architecture.md follows a
scan through the core):

1. **Motion prior** -- :class:`service.core.tracking.motion.Motion`: the odometry increment since
   the last scan when the scan carries ``odom`` (and ``motion.use_odometry``), else the robot's own
   smoothed velocity (the paper's no-odometry mode, §5.2);
2. **Scan polylines** (§4.1: grouping, angular order) --
   :func:`service.core.shapes.configuration.scan_groups`; their points are the points of the
   precise fit (the configuration's first-stage DCE, §4.2, waits for step 4);
3. **Precise fit** from the prior -- :func:`service.core.sensor.refine.refine_pose`: robust
   point-to-line against the whole map (:class:`service.core.sensor.mapmodel.MapModel`), the motion
   prior as a Gaussian term; its scan log-likelihood is the evidence;
4. **Shape matching** (§5: the map's abstract sensor reading from the prior, S*, the eq. 5
   dynamic programme, two-step matching) -- :func:`service.core.shapes.two_step.two_step_match` --
   runs when there is no odometry or the fit from the odometry prior is doubtful (far from
   the prior, low support, likelihood dropped): its correspondences give a pose beyond the
   fit's basin, which the precise fit then refines (unmatched scan polylines down-weighted);
5. **Arbitration** -- the candidate with the best scan likelihood weighed against the motion
   prior wins (schematic maps: the shape candidate when the shape match is good enough);
6. **Quality check** -- a fit that explains too little, or jumps beyond ``max_step`` /
   ``max_turn``, is rejected (the prior is kept); ``lost_after`` rejections in a row (with
   odometry: once the accumulated odometry uncertainty also exceeds ``lost_sigma_xy``) make
   the status ``lost``.

Frames and units: REP 103, metres and radians; poses ``[x, y, theta]`` in the map frame.
"""

from __future__ import annotations

import numpy as np

from service.core import numeric
from service.core.pose import compose
from service.core.sensor.mapmodel import MapModel
from service.core.sensor.refine import Refined, refine_pose, scan_normals
from service.core.sensor.scoring import SensorModel, WindowPeak, sensor_model
from service.core.shapes.configuration import (
    Configuration,
    MapViewCache,
    ScanGroups,
    scan_groups,
)
from service.core.shapes.two_step import TwoStepResult, two_step_match
from service.core.tracking.motion import Motion, Prediction, check_pose3
from service.core.tracking.shape_config import ShapeConfig
from service.core.types import Estimate, MapData, Match, Status, check_scan, wrap_angle
from service.errors import LocalizationError

__all__ = ["ShapeConfig", "ShapeLocalizer"]


class ShapeLocalizer:
    """Shape-based localiser of one robot (implements :class:`service.core.types.Localizer`).

    ``map_data`` the map; ``initial_pose`` ``[x, y, theta]`` (map frame) or ``None`` (unknown:
    every update answers ``initializing``; :mod:`service.core.reloc.global_localization` wraps this
    tracker with the global search); ``config`` a :class:`ShapeConfig` (default:
    :meth:`ShapeConfig.for_kind` of the map); ``model`` a shared
    :class:`~service.core.sensor.mapmodel.MapModel` of ``map_data`` (built if not given).

    Per scan (docs/architecture.md follows a scan through the core):

    1. the motion model (:class:`~service.core.tracking.motion.Motion`) predicts the pose -- the
       odometry increment when the scan carries ``odom``, else the robot's own velocity;
    2. the precise fit (:func:`~service.core.sensor.refine.refine_pose`) aligns the scan with the
       whole map from that prior;
    3. the shape matching of §4-§5 (grouping, DCE, S*, eq. 5 via
       :func:`~service.core.shapes.two_step.two_step_match`) runs when there is no odometry, or when
       the fit from the odometry prior is doubtful (its likelihood dropped, or it moved far
       from the prior): its correspondences give pose hypotheses beyond the fit's basin, each
       refined by the precise fit;
    4. the candidate with the best scan likelihood, weighed against the motion prior, wins;
       a scan whose best fit explains too little is rejected (the prior is kept) and enough
       rejections make the robot ``lost``.

    Deterministic: the same inputs give the same outputs. Not thread-safe.
    """

    method = "shape"

    def __init__(
        self,
        map_data: MapData,
        initial_pose: np.ndarray | None,
        config: ShapeConfig | None = None,
        *,
        model: MapModel | None = None,
    ) -> None:
        if config is not None and not isinstance(config, ShapeConfig):
            raise LocalizationError(f"config must be a ShapeConfig, got {type(config).__name__}")
        self.map_data = map_data
        self.config = config or ShapeConfig.for_kind(map_data.kind)
        self.sensor: SensorModel = sensor_model(map_data) if model is None else SensorModel(model)
        self.model = self.sensor.model
        self.motion = Motion(self.config.motion)
        #: The shape matching's settings for a turn recovery: cut points all round the circle.
        self._wide = self.config.model_copy(
            update={
                "heading_sweep": float(np.pi),
                "max_turn": float(np.pi),
                "heading_hypotheses": 4,
                "step2_hypotheses": 4,
                "fast_support": 1.01,
            }
        )
        self._params = self.config.extraction()
        # the velocity prior is weak on purpose: the points keep their full weight against it
        self._refine_velocity = self.config.refine.model_copy(update={"effective_points": 0.0})
        self._views = MapViewCache(
            map_data,
            beams=self.config.view_beams,
            max_range=self.config.view_max_range,
            reuse_distance=self.config.view_reuse_distance,
            params=self._params,
            model=self.model,
        )
        self._pose: np.ndarray | None = None
        self.reset(initial_pose)

    def __setstate__(self, state: dict[str, object]) -> None:
        self.__dict__.update(state)
        if "sensor" not in state:  # pickled by an earlier version: no sensor model yet
            self.sensor = SensorModel(self.model)

    @property
    def pose(self) -> np.ndarray | None:
        """Last accepted pose ``[x, y, theta]`` (map frame), ``None`` before a fix."""
        return None if self._pose is None else self._pose.copy()

    def reset(
        self,
        initial_pose: np.ndarray | None,
        odom: np.ndarray | None = None,
        known: tuple[float, float] | None = None,
    ) -> None:
        """Forget the history; ``None`` means the pose is unknown. ``odom``: odometry pose
        at ``initial_pose`` (the next scan's increment is measured from it). ``known``: how
        well ``initial_pose`` is known (position, heading sigmas; m, rad) -- the prior of
        the scan taken there (:meth:`service.core.tracking.motion.OdometryMotion.hold`)."""
        self._pose = None if initial_pose is None else check_pose3(initial_pose, "initial_pose")
        self._rejected = 0
        self._streak = 0  # scans accepted since the reset (the velocity is known after 3)
        self._drift = 0.0  # odometry position variance accumulated while scans are rejected
        self._typical: float | None = None  # recent typical log-likelihood of accepted fits
        self.motion.reset(None if initial_pose is None else odom, known)
        self._views.clear()
        #: How many scans ran the shape matching (for benchmarks and tests).
        self.shape_runs = 0
        #: The pose of the last scan's best fit, accepted or rejected (``None``: no fit was
        #: made). A rejected scan returns the prior; this says where the scan itself pointed.
        self.last_fit: np.ndarray | None = None

    def known_speed(self) -> np.ndarray | None:
        """The smoothed translation per scan (map frame, m) once three scans were accepted
        since the last reset, else ``None``."""
        return self.motion.velocity.velocity if self._streak >= 3 else None

    def set_speed(self, velocity: np.ndarray) -> None:
        """Carry a speed known from before a :meth:`reset` (losing and finding the track does
        not change how fast the robot moves): the step bound of ``speed_step_factor`` applies
        from the first scan."""
        self.motion.velocity.set_velocity(velocity)
        self._streak = max(self._streak, 3)

    def predict(self, delta: np.ndarray) -> None:
        """Move the current pose by a known relative motion ``delta`` ``[dx, dy, dtheta]``
        (robot frame) before the next :meth:`update`; no-op without a pose."""
        d = check_pose3(delta, "delta")
        if self._pose is not None:
            self._pose = compose(self._pose, d)

    # ------------------------------------------------------------------ internals
    def _fit_points(self, sg: ScanGroups) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Robot-frame points of the scan's grouped polylines (angular order), their normals
        and their rows in ``sg.points``, for the precise fit (returns beyond
        ``fit_max_range`` dropped, evenly thinned to ``fit_points``)."""
        cfg = self.config
        pts = sg.points
        if not len(pts):
            return np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, dtype=np.intp)
        nrm = scan_normals(pts, starts=sg.starts)
        rows = np.flatnonzero(np.hypot(pts[:, 0], pts[:, 1]) <= cfg.fit_max_range)
        if len(rows) > cfg.fit_points:
            rows = rows[np.linspace(0, len(rows) - 1, cfg.fit_points).round().astype(int)]
        return pts[rows], nrm[rows], rows

    def _refine(
        self,
        pts: np.ndarray,
        nrm: np.ndarray,
        start: np.ndarray,
        pred: Prediction,
        weights: np.ndarray | None = None,
    ) -> Refined:
        return refine_pose(
            self.model,
            pts,
            start,
            self.config.refine if pred.source == "odometry" else self._refine_velocity,
            normals=nrm,
            weights=weights,
            prior=pred.pose,
            prior_information=pred.information,
        )

    def _heading_starts(
        self, pts: np.ndarray, nrm: np.ndarray, pred: Prediction, weights: np.ndarray | None
    ) -> list[Refined]:
        """Fits from the odometry prior's position at its heading plus and minus half and
        one heading sigma, when that sigma exceeds ``heading_starts_sigma``: a fit from a
        heading a few degrees off can settle in a neighbouring basin (generated building 1000
        after a 119-degree turn between two processed scans, the odometry 3.2 degrees off: the
        fit from it 0.15 m off along a corridor, the one from 3.7 degrees the other side of the
        truth exact)."""
        lim = self.config.heading_starts_sigma
        sig = float(pred.sigma[2])
        if lim <= 0 or pred.source != "odometry" or sig <= lim:
            return []
        out = []
        for k in (-1.0, -0.5, 0.5, 1.0):
            start = pred.pose.copy()
            start[2] = wrap_angle(float(start[2]) + k * sig)
            out.append(self._refine(pts, nrm, start, pred, weights))
        return out

    def _score(
        self, f: Refined, pred: Prediction, weights: np.ndarray | None, violation: float = 0.0
    ) -> float:
        """Scan evidence (weighted mean log-likelihood, less ``violation_weight`` per share of
        beams through walls, x effective returns) minus the motion prior's squared
        Mahalanobis distance / 2: a log-posterior up to a constant."""
        e = f.pose - pred.pose
        e[2] = wrap_angle(float(e[2]))
        m2 = numeric.quadratic(e, pred.information)
        ll = f.loglik if weights is None else f.weighted_loglik(weights, self.config.refine)
        ll -= self.config.violation_weight * violation
        return self.config.evidence_points * ll - 0.5 * m2

    def _max_step(self, pred: Prediction) -> float:
        """How far (m) a scan may move the pose from the prior: ``max_step``, widened while
        scans are rejected, plus 3 sigma of an odometry prior."""
        cfg = self.config
        m = cfg.max_step
        if pred.source == "velocity" and cfg.speed_step_factor > 0 and self._streak >= 3:
            speed = float(np.hypot(*self.motion.velocity.velocity))
            m = min(m, cfg.speed_step_floor + cfg.speed_step_factor * speed)
        if pred.source == "odometry" and cfg.odom_step_floor > 0:
            m = min(m, cfg.odom_step_floor)
        m *= 1 + self._rejected
        if pred.source == "odometry":
            m += 3.0 * float(max(pred.sigma[0], pred.sigma[1]))
        return m

    def violations(
        self,
        r: np.ndarray,
        a: np.ndarray,
        poses: list[np.ndarray],
        margin: float | None = None,
    ) -> list[float]:
        """Per pose, the share of ``violation_beams`` evenly chosen valid beams whose return
        lies more than ``margin`` (default ``violation_margin``) beyond the range the map
        predicts from that pose (through a wall); the same beams for every pose."""
        cfg = self.config
        ok = np.nonzero(np.isfinite(r) & (r > 0.0))[0]
        if cfg.violation_beams == 0 or ok.size == 0:
            return [0.0] * len(poses)
        sel = ok[np.linspace(0, ok.size - 1, min(cfg.violation_beams, ok.size)).astype(np.intp)]
        rs, ang = r[sel], a[sel]
        m = cfg.violation_margin if margin is None else margin
        through = self.sensor.through(np.asarray(poses), rs, ang, m, cfg.view_max_range)
        return [float(v) for v in through]

    def window(
        self, r: np.ndarray, a: np.ndarray, center: np.ndarray, half_xy: float, half_th: float
    ) -> WindowPeak | None:
        """The sensor model's window search (:meth:`SensorModel.window`) of the scan's valid
        returns within ``fit_max_range`` around ``center``."""
        ok = np.isfinite(r) & (r > 0.0) & (r <= self.config.fit_max_range)
        pts = np.column_stack([r[ok] * np.cos(a[ok]), r[ok] * np.sin(a[ok])])
        return self.sensor.window(center, half_xy, half_th, pts)

    def _always_doubtful(self, pred: Prediction) -> bool:
        """The shape matching runs whatever the prior's fit: set so, or no odometry."""
        return self.config.shape_search == "always" or pred.source != "odometry"

    def _doubtful(self, f: Refined, pred: Prediction) -> bool:
        cfg = self.config
        if self._always_doubtful(pred):
            return True
        e = f.pose - pred.pose
        e[2] = wrap_angle(float(e[2]))
        if numeric.quadratic(e, pred.information) > cfg.doubt_mahalanobis:
            return True
        if f.inlier_fraction < cfg.min_support:
            return True
        return self._typical is not None and f.loglik < self._typical - cfg.doubt_loglik

    def update(
        self,
        ranges: np.ndarray,
        angles: np.ndarray,
        odom: np.ndarray | None = None,
        matched_from: np.ndarray | None = None,
        odom_spread: np.ndarray | None = None,
    ) -> Estimate:
        """Localise one scan. ``ranges`` metres (NaN = no return), ``angles`` radians in the
        robot frame (same length), ``odom`` optional odometry pose (own frame);
        ``matched_from`` the reading ``odom``'s increment was measured from by a scan-to-scan
        fit, if it was; ``odom_spread`` the increment's translation variance beyond the
        odometry model's, if any (both: :meth:`service.core.tracking.motion.MotionModel.predict`).

        Raises :class:`LocalizationError` on empty, mismatched, non-finite-angle or negative
        range input.
        """
        r, a = check_scan(ranges, angles)
        self.last_fit = None
        if self._pose is None:
            if odom is not None:
                check_pose3(odom, "odom")
            return Estimate(pose=np.zeros(3), status="initializing", score=0.0)
        cfg = self.config
        pred = self.motion.predict(self._pose, odom, matched_from, odom_spread)
        sg = scan_groups(r, a, self._params)
        pts, nrm, rows = self._fit_points(sg)
        if len(pts) < 3:
            return self._reject(pred, 0.0, (), 0.0, None, reason=1.0)
        # The prior's fit decides whether the shape matching runs; when it runs anyway and
        # weights its points, only the weighted fit below is used, so the plain one waits.
        always = self._always_doubtful(pred)
        prior_fit = None if always else self._refine(pts, nrm, pred.pose, pred)
        shape_fit: Refined | None = None
        matches: tuple[Match, ...] = ()
        explained: float | None = None
        ambiguity: float | None = None
        weights: np.ndarray | None = None
        extras: dict[str, float] = {}
        if always or (prior_fit is not None and self._doubtful(prior_fit, pred)):
            self.shape_runs += 1
            Q = self._views.view(pred.pose)
            if len(Q):
                P, own = sg.configuration, sg.feature_of_point[rows]
                two, matches, explained, weights = self._shape_match(P, Q, own, pred, cfg)
                ambiguity = two.ambiguity
                extras["step1_hypotheses"] = float(two.hypotheses)
                extras["eq5_cost"] = two.match.cost
                if weights is not None:
                    # the prior's fit again, now without the pull of unmatched structures
                    prior_fit = self._refine(pts, nrm, pred.pose, pred, weights)
                shape_fit = self._refine(pts, nrm, two.estimate, pred, weights)
        if prior_fit is None:
            prior_fit = self._refine(pts, nrm, pred.pose, pred)
        cands: list[tuple[str, Refined]] = [("prior", prior_fit)]
        cands += [("heading", f) for f in self._heading_starts(pts, nrm, pred, weights)]
        if shape_fit is not None:
            cands.append(("shape", shape_fit))
        shape_ok = (
            shape_fit is not None
            and len(matches) >= cfg.min_matches
            and (explained or 0.0) >= cfg.min_explained
        )
        # the "shape" arbiter stands in for a motion prior the velocity model cannot give;
        # with odometry the likelihood weighed against the prior decides on every map
        # (one candidate: nothing to weigh, the check is skipped)
        viol = self.violations(r, a, [f.pose for _n, f in cands]) if len(cands) > 1 else [0.0]
        if (
            cfg.arbiter == "shape"
            and shape_ok
            and pred.source != "odometry"
            and viol[-1] <= min(viol) + cfg.violation_slack
        ):
            name, best = cands[-1]
            k_best = len(cands) - 1
        else:
            scored = sorted(
                (
                    (self._score(f, pred, weights, viol[k]), k, n, f)
                    for k, (n, f) in enumerate(cands)
                ),
                key=lambda t: (-t[0], t[1]),
            )
            _, k_best, name, best = scored[0]
        if len(cands) > 1:
            extras["violation"] = viol[k_best]
        fit = best.fit
        self.last_fit = fit.pose.copy()
        sup = fit.inlier_fraction
        score = float(np.clip(sup if explained is None else 0.5 * (sup + explained), 0.0, 1.0))
        step = float(np.hypot(*(fit.pose[:2] - pred.pose[:2])))
        turn = abs(float(wrap_angle(fit.pose[2] - pred.pose[2])))
        extras.update(
            {
                "rms": fit.rms,
                "support": sup,
                "loglik": best.loglik,
                "shape_won": 1.0 if name == "shape" else 0.0,
                "step": step,
            }
        )
        if sup < cfg.min_support or step > self._max_step(pred) or turn > cfg.max_turn:
            rec = None
            if cfg.turn_recovery and pred.source != "odometry":
                own = sg.feature_of_point[rows]
                rec = self._recover(sg.configuration, pts, nrm, own, pred, sup)
            if rec is None:
                return self._reject(pred, score, matches, sup, ambiguity, 3.0, extras)
            best, matches, explained, weights = rec
            fit = best.fit
            self.last_fit = fit.pose.copy()
            sup = fit.inlier_fraction
            score = float(np.clip(0.5 * (sup + explained), 0.0, 1.0))
            extras.update(
                {
                    "rms": fit.rms,
                    "support": sup,
                    "loglik": best.loglik,
                    "shape_won": 1.0,
                    "step": float(np.hypot(*(fit.pose[:2] - pred.pose[:2]))),
                    "turn_recovered": abs(float(wrap_angle(fit.pose[2] - pred.pose[2]))),
                }
            )
        a_ = 0.1 if self._typical is not None else 1.0
        self._typical = (1 - a_) * (self._typical or 0.0) + a_ * best.loglik
        self.motion.accepted(self._pose, fit.pose)
        self._pose = fit.pose.copy()
        self._rejected = 0
        self._streak += 1
        self._drift = 0.0
        if explained is not None:
            extras["matched_share"] = explained
        return Estimate(
            pose=fit.pose.copy(),
            status="tracking",
            score=score,
            matches=matches,
            explained=sup,
            ambiguity=ambiguity,
            covariance=fit.covariance,
            extras=extras,
        )

    def _shape_match(
        self,
        P: Configuration,
        Q: Configuration,
        own: np.ndarray,
        pred: Prediction,
        config: ShapeConfig,
    ) -> tuple[TwoStepResult, tuple[Match, ...], float, np.ndarray | None]:
        """The two-step matching (§5.3) of scan ``P`` with map view ``Q`` from the prior, with
        ``config``'s hypotheses. Returns the result, its matches, the matched length share of
        the scan, and the precise fit's point weights (points of unmatched polylines at
        ``unmatched_weight``; ``None`` when that is 1 or nothing matched); ``own`` maps each
        fit point to its polyline."""
        scan_pts = np.vstack([f.points for f in P.features])
        two = two_step_match(P, Q, pred.pose, config, scan_pts, max_step=self._max_step(pred))
        matches = tuple(two.match.matches)
        total = sum(f.length for f in P.features)
        done = sum(P.features[i].length for m in matches for i in m.scan)
        explained = done / total if total > 0 else 0.0
        weights = None
        if matches and self.config.unmatched_weight < 1.0:
            matched = np.zeros(len(P.features), dtype=bool)
            matched[[i for m in matches for i in m.scan]] = True
            weights = np.where(matched[own], 1.0, self.config.unmatched_weight)
        return two, matches, explained, weights

    def _recover(
        self,
        P: Configuration,
        pts: np.ndarray,
        nrm: np.ndarray,
        own: np.ndarray,
        pred: Prediction,
        rejected_support: float,
    ) -> tuple[Refined, tuple[Match, ...], float, np.ndarray | None] | None:
        """Turn recovery (no odometry): the two-step matching from the prior position with
        cut-point hypotheses all round the circle, the precise fit from its estimate with the
        prior's heading term dropped. Returns ``(fit, matches, matched share, weights)`` when
        the result passes every bar the ordinary path has (support, matched share, step) and
        explains more than the rejected fit did; ``None`` otherwise."""
        cfg = self.config
        Q = self._views.view(pred.pose)
        if not len(Q):
            return None
        self.shape_runs += 1
        two, matches, explained, weights = self._shape_match(P, Q, own, pred, self._wide)
        if len(matches) < cfg.min_matches or explained < cfg.min_explained:
            return None
        info = pred.information.copy()
        info[2, :] = 0.0
        info[:, 2] = 0.0
        free = Prediction(pose=pred.pose, information=info, source=pred.source)
        f = self._refine(pts, nrm, two.estimate, free, weights)
        sup = f.fit.inlier_fraction
        step = float(np.hypot(*(f.fit.pose[:2] - pred.pose[:2])))
        if sup < cfg.min_support or sup <= rejected_support or step > self._max_step(pred):
            return None
        return f, matches, explained, weights

    def _reject(
        self,
        pred: Prediction,
        score: float,
        matches: tuple[Match, ...],
        explained: float | None,
        ambiguity: float | None,
        reason: float,
        extras: dict[str, float] | None = None,
    ) -> Estimate:
        """The scan could not be matched well: keep the prior, count towards 'lost'."""
        self._rejected += 1
        self._pose = pred.pose.copy()
        self.motion.rejected()
        sig = pred.sigma
        self._drift += float(sig[0] ** 2 + sig[1] ** 2)
        lost = self._rejected >= self.config.lost_after
        if pred.source == "odometry":
            lost = lost and np.sqrt(self._drift) > self.config.lost_sigma_xy
        status: Status = "lost" if lost else "tracking"
        return Estimate(
            pose=pred.pose.copy(),
            status=status,
            score=float(score),
            matches=matches,
            explained=explained,
            ambiguity=ambiguity,
            extras={**(extras or {}), "rejected": reason},
        )
