"""Shape-based localisation (SBL, paper §4-§6): :class:`ShapeConfig` and :class:`ShapeLocalizer`.

Per scan (:meth:`ShapeLocalizer.update`):

1. the scan's configuration (§4.1-4.2: grouping, first-stage DCE) in the robot frame —
   :func:`service.core.configuration.scan_configuration`;
2. the map's abstract sensor reading from the last pose (§5.2) — a cached 360-degree map view,
   :class:`service.core.configuration.MapViewCache`;
3. two-step matching (§5.3): displacement estimate from the most complex / most similar pairs,
   then the full eq. 5 dynamic programme — :func:`service.core.matching.two_step_match`;
4. the pose by least squares over points of the matched pairs only —
   :func:`service.core.pose.pose_from_matches`;
5. a quality check deciding ``tracking`` / ``lost``.

No odometry is needed (§5.2); ``odom`` may seed the prior when ``use_odometry`` is set.
Frames and units: REP 103, metres and radians; poses ``[x, y, theta]`` in the map frame.
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.core.configuration import ExtractionParams, MapViewCache, scan_configuration
from service.core.dce import DCE_NOISE_THRESHOLD
from service.core.matching import matched_pairs, support, two_step_match
from service.core.pose import compose, invert, pose_from_matches
from service.core.types import Estimate, MapData, Match, Status, wrap_angle
from service.errors import LocalizationError


class ShapeConfig(BaseModel):
    """Every weight and threshold of the shape-based method, in one model.

    Defaults are the values for an exact **metric** map; :meth:`for_kind` returns the
    **schematic** variant (fields marked "schematic: ..." differ). Units: metres, radians;
    "cost" means the metres-like unit of S* and eq. 4.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["metric", "schematic"] = Field("metric", description="Map kind these suit.")
    # --- extraction (§4.1), shared by scan and map view -----------------------------------
    min_object_distance: float = Field(0.10, gt=0, description="Grouping threshold floor (m).")
    range_factor: float = Field(4.0, gt=0, description="Range-adaptive grouping factor.")
    min_points: int = Field(3, ge=2, description="Smallest group kept (points).")
    min_length: float = Field(0.05, ge=0, description="Shortest polyline kept (m).")
    dce_threshold: float = Field(
        DCE_NOISE_THRESHOLD, gt=0, description="First-stage DCE stop relevance, eq. 2 (m)."
    )
    piece_length: float = Field(
        1.5,
        ge=0,
        description="Cut polylines at vertices into pieces of about this length "
        "(m, 0 = off), so a room seen in one sweep becomes wall-sized features.",
    )
    # --- map view (§5.2) -------------------------------------------------------------------
    view_beams: int = Field(720, ge=8, description="Virtual beams of the 360-degree map view.")
    view_max_range: float = Field(15.0, gt=0, description="Map view range limit (m).")
    view_reuse_distance: float = Field(
        0.1, ge=0, description="Reuse the last map view while the pose moved less (m)."
    )
    # --- eq. 5 and eq. 4 -------------------------------------------------------------------
    penalty_weight: float = Field(
        1.0,
        ge=0,
        description="R per radian of angular size of an unmatched polyline (cost). Schematic: 1.5.",
    )
    map_penalty_factor: float = Field(
        1.0, ge=0, description="Extra factor on R for unmatched map polylines."
    )
    rotation_weight: float = Field(10.0, ge=0, description="Eq. 4: weight of |dPhi| (m/rad).")
    consistency_weight: float = Field(1.0, ge=0, description="Weight of ΔA (eq. 4) in eq. 5.")
    max_consistency: float = Field(
        0.6,
        gt=0,
        description="Gate: pairs with ΔA above this never correspond (cost). Schematic: 1.0.",
    )
    max_shape_distance: float = Field(
        1.5, gt=0, description="Gate: only shapes with S* below this correspond (m)."
    )
    bearing_gate: float = Field(
        0.35, ge=0, description="Angular slack (rad) for candidate pairs in step 2."
    )
    shape_end_weight: float = Field(
        0.1,
        ge=0,
        description="S*: weight of the end arcs' length misfit (occlusion cuts). "
        "Schematic: 0.02 (map walls are long, the scan sees parts of them).",
    )
    shape_skip_weight: float = Field(
        0.5,
        ge=0,
        description="S*: cost per metre of whole end arcs without counterpart. Schematic: 0.1.",
    )
    max_join: int = Field(3, ge=1, description="Max polylines concatenated per side (n:m).")
    join_total: bool = Field(
        True,
        description="Limit blocks to max_join polylines on both sides together "
        "(1:1, 1:2, 2:1, ...) instead of max_join on each side.",
    )
    align_points: int = Field(
        24,
        ge=3,
        description="Scan points per step-1 pair for A(P, Q); half per polyline in step 2.",
    )
    align_iterations: int = Field(3, ge=1, description="Gauss-Newton steps for A(P, Q).")
    align_robust_scale: float = Field(
        0.1, gt=0, description="Cauchy scale of A(P, Q)'s fit (m). Schematic: 0.2."
    )
    align_damping: float = Field(
        0.05, ge=0, description="Levenberg damping of A(P, Q)'s fit (relative to the trace)."
    )
    # --- two-step matching (§5.3) ----------------------------------------------------------
    two_step: bool = Field(True, description="Run step 1 (complex pairs) before step 2.")
    step1_features: int = Field(6, ge=1, description="Most complex scan polylines used.")
    step1_min_complexity: float = Field(
        0.05, ge=0, description="Minimum shape complexity for step 1 (m·rad)."
    )
    step1_range_gate: float = Field(
        0.8, gt=0, description="Step 1: |range difference| allowed for a candidate pair (m)."
    )
    step1_max_shape_distance: float = Field(
        0.8, gt=0, description="Step 1: S* gate for the most similar pairs (m)."
    )
    step1_pairs_per_feature: int = Field(3, ge=1, description="Step 1: pairs kept per feature.")
    step1_refine_iterations: int = Field(
        5, ge=0, description="Step 1: point-to-line refinement steps of each pair's alignment."
    )
    fast_support: float = Field(
        0.9,
        ge=0,
        le=1.01,
        description="If the prior explains this fraction of the scan, skip step 1 and the "
        "heading sweep (small motion). Schematic: 1.01 (never; furniture is missing).",
    )
    fast_sweep: float = Field(
        0.2, ge=0, description="Fast path: heading sweep half-width around the prior (rad)."
    )
    fast_bearing_gate: float = Field(
        0.12, ge=0, description="Fast path: angular slack (rad) for candidate pairs."
    )
    fast_step: float = Field(0.01, gt=0, description="Fast path: heading sweep step (rad).")
    step2_hypotheses: int = Field(3, ge=1, description="Hypotheses run through step 2.")
    heading_sweep: float = Field(
        1.3,
        ge=0,
        description="Cut-point hypotheses: headings within this of the prior (rad, 0 = off).",
    )
    heading_step: float = Field(0.06, gt=0, description="Heading sweep step (rad).")
    heading_hypotheses: int = Field(2, ge=1, description="Best heading peaks kept.")
    step2_refinements: int = Field(
        1, ge=0, description="Step 2 re-runs with the estimate re-fitted on its own matches."
    )
    support_points: int = Field(120, ge=10, description="Scan points used to score support.")
    support_tolerance: float = Field(
        0.1,
        gt=0,
        description="Distance (m) within which a scan point is explained. Schematic: 0.25.",
    )
    # --- pose (least squares over matched pairs) -------------------------------------------
    pose_iterations: int = Field(12, ge=1, description="Re-pairing iterations of the pose.")
    pose_inlier_distance: float = Field(
        0.3,
        gt=0,
        description="Points farther from their pair's map polyline are dropped (m). "
        "Schematic: 0.4.",
    )
    pose_robust_scale: float = Field(
        0.03, gt=0, description="Cauchy scale of the pose fit (m). Schematic: 0.08."
    )
    pose_prior_weight: float = Field(
        0.0,
        ge=0,
        description="Pull of the position towards the prior in the pose fit "
        "(equivalent pinned points); matters only along unobservable directions.",
    )
    prior_distance_weight: float = Field(
        1.0,
        ge=0,
        description="Cost per metre between a step-2 hypothesis and the prior "
        "position, added when ranking hypotheses.",
    )
    # --- quality / status ------------------------------------------------------------------
    min_matches: int = Field(2, ge=1, description="Fewer matched pairs: the scan is rejected.")
    min_explained: float = Field(
        0.25, ge=0, le=1, description="Minimum matched fraction of the scan's polyline length."
    )
    min_support: float = Field(
        0.3, ge=0, le=1, description="Minimum fraction of scan points explained at the pose."
    )
    max_step: float = Field(
        0.5,
        gt=0,
        description="Largest travel between two scans (m): farther step-1 hypotheses and "
        "pose jumps are rejected.",
    )
    max_turn: float = Field(
        1.3,
        gt=0,
        description="Largest turn between two scans (rad): farther-turned hypotheses and "
        "poses are rejected.",
    )
    lost_after: int = Field(3, ge=1, description="Consecutive rejected scans before 'lost'.")
    use_odometry: bool = Field(False, description="Seed the prior with the odometry delta.")
    extrapolate: bool = Field(
        True,
        description="Seed the prior position with the localiser's own recent translation per "
        "scan (no odometry): where a corridor leaves the position along it unobservable the "
        "estimate keeps moving instead of lagging behind.",
    )
    velocity_smoothing: float = Field(
        0.5, ge=0, le=1, description="Weight of the newest translation in the velocity average."
    )

    @classmethod
    def for_kind(cls, kind: str) -> ShapeConfig:
        """Defaults for a map ``kind`` (``metric`` or ``schematic``)."""
        if kind == "metric":
            return cls()
        if kind == "schematic":
            return cls(
                kind="schematic",
                max_consistency=1.0,
                shape_end_weight=0.02,
                shape_skip_weight=0.1,
                align_robust_scale=0.2,
                support_tolerance=0.25,
                fast_support=1.01,
                penalty_weight=1.5,
                pose_inlier_distance=0.4,
                pose_robust_scale=0.08,
            )
        raise LocalizationError(f"unknown map kind {kind!r}; expected metric or schematic")

    def extraction(self) -> ExtractionParams:
        """The extraction parameters shared by scans and map views."""
        return ExtractionParams(
            min_object_distance=self.min_object_distance,
            range_factor=self.range_factor,
            min_points=self.min_points,
            dce_threshold=self.dce_threshold,
            min_length=self.min_length,
            piece_length=self.piece_length,
        )


def _check_pose(p: Any, what: str) -> np.ndarray:
    a = np.asarray(p, dtype=np.float64)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise LocalizationError(f"{what}: expected 3 finite values [x, y, theta], got {a.shape}")
    return np.array([a[0], a[1], wrap_angle(float(a[2]))])


class ShapeLocalizer:
    """Shape-based localiser of one robot (implements :class:`service.core.types.Localizer`).

    ``map_data`` the map; ``initial_pose`` ``[x, y, theta]`` (map frame) or ``None`` (unknown:
    global localisation is not implemented yet, every update answers ``initializing``);
    ``config`` a :class:`ShapeConfig` (default: :meth:`ShapeConfig.for_kind` of the map).
    Deterministic: the same inputs give the same outputs. Not thread-safe.
    """

    method = "shape"

    def __init__(
        self,
        map_data: MapData,
        initial_pose: np.ndarray | None,
        config: ShapeConfig | None = None,
    ) -> None:
        if config is not None and not isinstance(config, ShapeConfig):
            raise LocalizationError(f"config must be a ShapeConfig, got {type(config).__name__}")
        self.map_data = map_data
        self.config = config or ShapeConfig.for_kind(map_data.kind)
        self._params = self.config.extraction()
        self._views = MapViewCache(
            map_data,
            beams=self.config.view_beams,
            max_range=self.config.view_max_range,
            reuse_distance=self.config.view_reuse_distance,
            params=self._params,
        )
        self._pose: np.ndarray | None = None
        self._last_odom: np.ndarray | None = None
        self._rejected = 0
        self.reset(initial_pose)

    @property
    def pose(self) -> np.ndarray | None:
        """Last accepted pose ``[x, y, theta]`` (map frame), ``None`` before a fix."""
        return None if self._pose is None else self._pose.copy()

    def reset(self, initial_pose: np.ndarray | None) -> None:
        """Forget the history; ``None`` means the pose is unknown."""
        self._pose = None if initial_pose is None else _check_pose(initial_pose, "initial_pose")
        self._last_odom = None
        self._rejected = 0
        self._velocity = np.zeros(2)
        self._views.clear()

    def predict(self, delta: np.ndarray) -> None:
        """Move the current pose by a known relative motion ``delta`` ``[dx, dy, dtheta]``
        (robot frame, e.g. an odometry delta) before the next :meth:`update`; no-op without a
        pose. For motions the matching alone cannot bridge (turns beyond ``max_turn``)."""
        d = _check_pose(delta, "delta")
        if self._pose is not None:
            self._pose = compose(self._pose, d)

    def _prior(self, odom: np.ndarray | None) -> np.ndarray:
        assert self._pose is not None
        prior = self._pose
        if self.config.extrapolate:
            prior = np.array([prior[0] + self._velocity[0], prior[1] + self._velocity[1], prior[2]])
        if odom is not None:
            o = _check_pose(odom, "odom")
            if self.config.use_odometry and self._last_odom is not None:
                delta = compose(invert(self._last_odom), o)
                prior = compose(prior, delta)
            self._last_odom = o
        return prior

    def update(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None = None
    ) -> Estimate:
        """Localise one scan. ``ranges`` metres (NaN = no return), ``angles`` radians in the
        robot frame (same length), ``odom`` optional odometry pose (own frame).

        Raises :class:`LocalizationError` on empty, mismatched, non-finite-angle or negative
        range input.
        """
        r = np.asarray(ranges, dtype=np.float64)
        a = np.asarray(angles, dtype=np.float64)
        if r.ndim != 1 or a.ndim != 1 or r.shape != a.shape:
            raise LocalizationError(
                f"ranges and angles must be 1-D of equal length, got {r.shape} and {a.shape}"
            )
        if r.size == 0:
            raise LocalizationError("empty scan")
        if not np.all(np.isfinite(a)):
            raise LocalizationError("beam angles must be finite")
        if np.any(np.isinf(r)) or np.any(r[~np.isnan(r)] < 0):
            raise LocalizationError("ranges must be >= 0 or NaN (no return)")
        if self._pose is None:
            return Estimate(pose=np.zeros(3), status="initializing", score=0.0)
        cfg = self.config
        prior = self._prior(odom)
        P = scan_configuration(r, a, self._params)
        Q = self._views.view(prior)
        if len(P) == 0 or len(Q) == 0:
            return self._reject(prior, 0.0, (), 0.0, None, reason=1.0)
        scan_pts = np.vstack([f.points for f in P.features])
        # While scans are rejected the robot keeps moving: widen the admissible step.
        max_step = cfg.max_step * (1 + self._rejected)
        two = two_step_match(P, Q, prior, cfg, scan_pts, max_step=max_step)
        matches = tuple(two.match.matches)
        total_len = sum(f.length for f in P.features)
        matched_len = sum(P.features[i].length for m in matches for i in m.scan)
        explained = matched_len / total_len if total_len > 0 else 0.0
        if len(matches) < cfg.min_matches:
            return self._reject(prior, 0.0, matches, explained, two.ambiguity, reason=2.0)
        pairs = matched_pairs(P, Q, matches)
        fit = pose_from_matches(
            pairs,
            two.estimate,
            iterations=cfg.pose_iterations,
            inlier_distance=cfg.pose_inlier_distance,
            robust_scale=cfg.pose_robust_scale,
            prior=prior,
            prior_weight=cfg.pose_prior_weight,
        )
        sup = support(
            Q,
            scan_pts[:: max(1, len(scan_pts) // cfg.support_points)],
            fit.pose,
            cfg.support_tolerance,
        )
        step = float(np.hypot(*(fit.pose[:2] - prior[:2])))
        score = float(np.clip(0.5 * sup + 0.5 * explained, 0.0, 1.0))
        extras = {
            "rms": fit.rms,
            "support": sup,
            "inlier_fraction": fit.inlier_fraction,
            "step1_hypotheses": float(two.hypotheses),
            "eq5_cost": two.match.cost,
        }
        turn = abs(float(wrap_angle(fit.pose[2] - prior[2])))
        if (
            explained < cfg.min_explained
            or sup < cfg.min_support
            or step > max_step
            or turn > cfg.max_turn
        ):
            extras["step"] = step
            return self._reject(
                prior, score, matches, explained, two.ambiguity, reason=3.0, extras=extras
            )
        v = fit.pose[:2] - self._pose[:2]
        a = cfg.velocity_smoothing
        self._velocity = (1.0 - a) * self._velocity + a * v
        vn = float(np.hypot(*self._velocity))
        if vn > 0.5 * cfg.max_step:
            self._velocity *= 0.5 * cfg.max_step / vn
        self._pose = fit.pose.copy()
        self._rejected = 0
        return Estimate(
            pose=fit.pose.copy(),
            status="tracking",
            score=score,
            matches=matches,
            explained=float(explained),
            ambiguity=two.ambiguity,
            covariance=fit.covariance,
            extras=extras,
        )

    def _reject(
        self,
        prior: np.ndarray,
        score: float,
        matches: tuple[Match, ...],
        explained: float,
        ambiguity: float | None,
        reason: float,
        extras: dict[str, float] | None = None,
    ) -> Estimate:
        """The scan could not be matched well: keep the prior, count towards 'lost'."""
        self._rejected += 1
        self._pose = prior.copy()
        self._velocity *= 0.5  # do not coast on while nothing confirms the motion
        status: Status = "lost" if self._rejected >= self.config.lost_after else "tracking"
        return Estimate(
            pose=prior.copy(),
            status=status,
            score=float(score),
            matches=matches,
            explained=float(explained),
            ambiguity=ambiguity,
            extras={**(extras or {}), "rejected": reason},
        )
