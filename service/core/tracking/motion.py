"""Motion models: where the robot should be now, and how sure we are (one seam for every method).

A :class:`MotionModel` turns the last pose and the scan's optional odometry into a *prior*
pose with an *information matrix* (inverse covariance, map frame, ``[x, y, theta]``), the
way AMCL's motion models seed its particles. Every localisation method (``shape``, ``icp``,
``lines``) asks the same model:

* :class:`OdometryMotion` -- the scan carries ``odom`` (the odometry pose in its own frame):
  the prior is ``last_pose (+) (odom_prev^-1 (+) odom)``, the increment since the previous
  scan; its uncertainty grows with the distance driven and the angle turned (the
  ``alpha`` parameters of the classic odometry model, as in AMCL's ``diff`` model).
  **Stale odometry**: a reading bit-identical to the previous one is not a stop but an
  odometry that was not updated (real logs: mit-csail's odometry freezes for a few scans,
  then jumps 0.7-0.9 m at once; intel once). Such a scan gets a *hold* prior (the last pose,
  with the velocity model's weak sigmas, source ``"held"``: the scan decides), and the next
  fresh reading's increment is applied to the pose estimated at the scan where the previous
  reading was taken, so motion that the held scans already tracked is not counted twice.
  One exception: the first scan that repeats the reading given to ``reset`` (a restart or a
  confirmed global fix, both measured from that reading) was taken where that reading was,
  so its fit, not the reset pose, anchors the next increment.
* :class:`VelocityMotion` -- no odometry (the seed's experiment, ``--no-odom``): the robot is
  assumed to keep its recent translation per scan (smoothed), heading unchanged; the prior is
  weak, so the scan decides.

:class:`Motion` picks per scan: odometry when the scan has it and ``use_odometry`` is on,
else the velocity model (a scan without ``odom`` after scans with it falls back cleanly).
Frames and units: REP 103, metres and radians; odometry increments are in the robot frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np
from pydantic import ConfigDict, Field

from service.core import numeric
from service.core.pose import compose, invert
from service.core.types import Settings, wrap_angle
from service.errors import LocalizationError

Source = Literal["odometry", "velocity", "held"]


class ScanOdometryConfig(Settings):
    """Parameters of :class:`service.core.tracking.scan_odometry.ScanOdometry`: the odometry
    increments corrected by matching each scan to the previous one (metres, radians)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    enabled: bool = Field(
        True,
        description="Correct each odometry increment by matching the scan to the previous "
        "one (off: the odometry as received).",
    )
    max_points: int = Field(
        120, ge=10, description="New-scan points fitted (evenly subsampled by beam)."
    )
    max_range: float = Field(
        15.0, gt=0, description="Returns farther than this (m) are left out of the fit."
    )
    iterations: int = Field(10, ge=1, description="Gauss-Newton steps (re-associated each).")
    gate_initial: float = Field(
        0.5, gt=0, description="Association distance (m) of the first step ..."
    )
    gate_final: float = Field(0.15, gt=0, description="... shrinking to this by the last.")
    robust_scale: float = Field(0.05, gt=0, description="Cauchy scale of the residuals (m).")
    normal_window: int = Field(
        5,
        ge=1,
        description="A point's surface normal is fitted to the returns within this "
        "many beams on either side ...",
    )
    normal_radius: float = Field(0.2, gt=0, description="... and this distance (m) of it.")
    max_flatness: float = Field(
        0.1,
        gt=0,
        description="... when they lie on a line: the smaller spread at most this share of "
        "the larger (else no normal: a corner, or clutter).",
    )
    normal_gate: float = Field(
        0.8,
        gt=0,
        le=math.pi / 2,
        description="A point pairs only with a previous point whose surface normal agrees "
        "within this (rad): where the previous scan saw one wall and this one the wall "
        "round the corner, pairing across the corner would drag the fit.",
    )
    min_constraint: float = Field(
        0.05,
        gt=0,
        le=0.5,
        description="The fit corrects the position only along directions that at least this "
        "share of the points' weight observes (their normals' projection; "
        "scan_odometry.observed): elsewhere, e.g. along a corridor, the odometry holds.",
    )
    point_sigma: float = Field(0.03, gt=0, description="Residual sigma of one point (m).")
    effective_points: int = Field(
        40,
        ge=1,
        description="The points count as at most this many independent ones against the "
        "prior (neighbouring returns' errors are correlated).",
    )
    inlier_tolerance: float = Field(
        0.05, gt=0, description="A point within this (m) of the previous scan is explained."
    )
    min_inliers: float = Field(
        0.5,
        gt=0,
        le=1,
        description="The fit is kept only when it explains at least this share of the points "
        "(else the raw increment is used: the scans do not overlap enough).",
    )
    fallback_sigma: float = Field(
        0.0,
        ge=0,
        description="A fit that explains less than min_inliers of the points is tried again "
        "from no translation (the odometry's turn kept) under this position sigma (m): the "
        "odometry's own increment may be what is wrong (the tuning log fr079 counts forward "
        "while the robot backs up; a wheel slips). Kept when it explains at least "
        "min_inliers and fallback_gain more than the first fit. 0 = off, the default; 0.5 "
        "for a robot whose odometry can be wrong by more than 0.5 m between two scans "
        "(scans far apart, encoders that do not count backwards): on the tuning log fr079 "
        "fed every 3rd scan it corrects 11 of the 14 increments left > 0.2 m off. Off by "
        "default because on intel fed every scan it breaks a self-cancelling odometry "
        "glitch (scans 12710-12712: 0.7 m back, 0.8 m forward; only the second is "
        "replaced), and the drive bench then has 9 tracking poses off after a fix.",
    )
    fallback_gain: float = Field(
        0.2,
        ge=0,
        le=1,
        description="See fallback_sigma: the share of the points the fallback fit must "
        "explain beyond the first fit. On fr079 fed every 2nd / 3rd scan the fits that "
        "found its backward drives gained 0.30-0.59; the two on intel fed every scan that "
        "gained 0.05 and 0.12 moved a robot whose odometry turned on the spot, or stood, "
        "0.2 m (translation p99 of intel's increments 0.160 -> 0.181 m with them).",
    )


class MotionConfig(Settings):
    """Parameters of the motion models (metres, radians). Tuned on the intel and fr079 logs."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    use_odometry: bool = Field(
        True,
        description="Use a scan's odometry increment as the prior when the scan carries "
        "'odom' (off: the paper's no-odometry mode even when odometry is sent).",
    )
    alpha_rot_rot: float = Field(0.1, ge=0, description="Rotation noise per radian turned.")
    alpha_rot_trans: float = Field(0.05, ge=0, description="Rotation noise (rad) per metre driven.")
    alpha_trans_trans: float = Field(0.1, ge=0, description="Translation noise per metre driven.")
    alpha_trans_rot: float = Field(0.05, ge=0, description="Translation noise (m) per radian.")
    matched_turn_noise: float = Field(
        0.0,
        ge=0,
        le=1,
        description="Share of the turn terms (alpha_rot_rot, alpha_trans_rot) kept in the "
        "sigmas of an increment measured by a kept scan-to-scan fit "
        "(service.core.tracking.scan_odometry; 1 = as a raw increment's). Two scans tell a turn as "
        "well as a straight step: on the tuning logs the corrected increments' heading error "
        "p90 is 1.0-1.8 deg in every turn bin from 0 to 0.6 rad and beyond, while the raw "
        "odometry's grows with the turn (fr079 1.7 -> 3.3 deg, intel 5.4 -> 9.5; "
        "bench/bench_odometry.py). With the turn terms, the floor-plan tracker of tuning "
        "building 16, whose scans come 0.1 m apart with turns of up to 150 deg between them, "
        "slid 0.8 m / 17 deg onto furniture within 10 scans.",
    )
    sigma_xy_floor: float = Field(
        0.03, gt=0, description="Smallest odometry position sigma per scan (m)."
    )
    sigma_theta_floor: float = Field(
        0.02, gt=0, description="Smallest odometry heading sigma per scan (rad)."
    )
    extrapolate: bool = Field(
        True,
        description="Without odometry, extrapolate the robot's recent velocity (off: the prior "
        "is the previous pose, as the paper's baselines do).",
    )
    velocity_smoothing: float = Field(
        0.5, ge=0, le=1, description="Weight of the newest translation in the velocity average."
    )
    max_velocity: float = Field(
        0.25, gt=0, description="Cap of the extrapolated translation per scan (m)."
    )
    velocity_sigma_xy: float = Field(
        0.3, gt=0, description="Position sigma of the velocity prior (m): weak on purpose."
    )
    velocity_sigma_theta: float = Field(
        0.6, gt=0, description="Heading sigma of the velocity prior (rad): weak on purpose."
    )
    scan_odometry: ScanOdometryConfig = Field(
        default_factory=ScanOdometryConfig,
        description="Odometry increments corrected by matching each scan to the previous one "
        "(service.core.tracking.scan_odometry), before any use of the odometry.",
    )


@dataclass(frozen=True)
class Prediction:
    """A prior pose ``[x, y, theta]`` (map frame) with its 3x3 information matrix (map frame,
    1/m^2 and 1/rad^2), where it came from, and the odometry increment used (robot frame,
    ``None`` without odometry)."""

    pose: np.ndarray
    information: np.ndarray
    source: Source
    delta: np.ndarray | None = None

    @property
    def sigma(self) -> np.ndarray:
        """Standard deviations ``[sx, sy, stheta]`` of the prior (diagonal of its covariance)."""
        return np.sqrt(1.0 / np.maximum(np.diag(self.information), 1e-12))


class MotionModel(Protocol):
    """The seam every method uses to predict the pose of the next scan."""

    def reset(
        self, odom: np.ndarray | None = None, known: tuple[float, float] | None = None
    ) -> None:
        """Forget odometry and velocity history (new start pose); ``odom``, when given, is
        the odometry pose at that start: the next increment is measured from it. ``known``:
        how well the start pose is known (position, heading sigmas; m, rad), for the scan
        taken there (see :meth:`OdometryMotion.hold`); ``None``: it is not."""
        ...

    def predict(
        self,
        pose: np.ndarray,
        odom: np.ndarray | None,
        matched_from: np.ndarray | None = None,
        spread: np.ndarray | None = None,
    ) -> Prediction:
        """Prior for the scan that carries ``odom`` (or ``None``), from the last ``pose``.
        ``matched_from``: the odometry reading ``odom``'s increment was measured from by a
        kept scan-to-scan fit
        (:attr:`service.core.tracking.scan_odometry.ScanOdometry.matched_from`), ``None`` if it
        was not. ``spread``: translation variance (2x2, m^2, robot frame of the previous
        reading) the increment carries beyond the odometry model's
        (:attr:`service.core.tracking.laser_odometry.LaserStep.spread`), ``None``: none."""
        ...

    def accepted(self, previous: np.ndarray, pose: np.ndarray) -> None:
        """The scan was localised: ``previous`` -> ``pose`` is the motion it showed."""
        ...

    def rejected(self) -> None:
        """The scan could not be localised (the prior was kept)."""
        ...


def odometry_sigmas(
    delta: np.ndarray, c: MotionConfig, matched: bool = False
) -> tuple[float, float]:
    """Position and heading sigmas (m, rad) of one odometry increment ``delta`` (robot
    frame): ``floor + alpha * distance + alpha * angle`` (the ``alpha`` parameters of the
    classic odometry model). ``matched``: the increment was measured by a kept scan-to-scan
    fit, whose error does not grow with the turn: the angle terms are scaled by
    ``c.matched_turn_noise``."""
    d = float(np.hypot(delta[0], delta[1]))
    t = abs(float(delta[2])) * (c.matched_turn_noise if matched else 1.0)
    s_trans = c.sigma_xy_floor + c.alpha_trans_trans * d + c.alpha_trans_rot * t
    s_rot = c.sigma_theta_floor + c.alpha_rot_rot * t + c.alpha_rot_trans * d
    return s_trans, s_rot


def check_pose3(p: object, what: str) -> np.ndarray:
    """``[x, y, theta]`` as float64 with theta wrapped; :class:`LocalizationError` otherwise."""
    a = np.asarray(p, dtype=np.float64)
    if a.shape != (3,):
        raise LocalizationError(f"{what}: expected 3 finite values [x, y, theta], got {a.shape}")
    x, y, t = a.tolist()  # Python floats: a scan checks its poses several times
    if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(t)):
        raise LocalizationError(f"{what}: expected 3 finite values [x, y, theta], got {a.shape}")
    return np.array([x, y, wrap_angle(t)])


def _information(theta: float, sx: float, sy: float, st: float) -> np.ndarray:
    """Information matrix (map frame) of independent robot-frame sigmas ``sx`` (forward),
    ``sy`` (left) and ``st`` (heading) at heading ``theta``."""
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[c, -s], [s, c]])
    info = np.zeros((3, 3))
    info[:2, :2] = numeric.matmul(numeric.matmul(R, np.diag([1.0 / sx**2, 1.0 / sy**2])), R.T)
    info[2, 2] = 1.0 / st**2
    return info


def _spread_information(theta: float, s_trans: float, spread: np.ndarray) -> np.ndarray:
    """Position information (2x2, map frame) of an increment with isotropic sigma ``s_trans``
    plus the variance ``spread`` (2x2, robot frame at heading ``theta``)."""
    sp = np.asarray(spread, dtype=np.float64).reshape(2, 2)
    if not np.all(np.isfinite(sp)):
        raise LocalizationError("odometry spread must be finite")
    c, s = np.cos(theta), np.sin(theta)
    R = np.array([[c, -s], [s, c]])
    cov = s_trans**2 * np.eye(2) + numeric.matmul(numeric.matmul(R, 0.5 * (sp + sp.T)), R.T)
    return numeric.inv(cov)


class OdometryMotion:
    """Odometry increment as the prior (see the module docstring); sigmas per scan:
    ``s_trans = floor + alpha_trans_trans * d + alpha_trans_rot * |dtheta|`` and
    ``s_rot = floor + alpha_rot_rot * |dtheta| + alpha_rot_trans * d``."""

    def __init__(self, config: MotionConfig) -> None:
        self.config = config
        self._last: np.ndarray | None = None
        self._anchor: np.ndarray | None = None  # pose estimate where ``_last`` was taken
        self._fresh = True  # the previous predict used a fresh reading
        self._at_reset = False  # ``_last`` is the reset's reading, no scan has used it yet
        self._known: tuple[float, float] | None = None  # the reset pose's sigmas, if known

    def reset(
        self, odom: np.ndarray | None = None, known: tuple[float, float] | None = None
    ) -> None:
        self._last = None if odom is None else check_pose3(odom, "odom")
        self._anchor = None
        self._fresh = True
        self._at_reset = odom is not None
        self._known = known if odom is not None else None

    def stale(self, odom: np.ndarray) -> bool:
        """``True`` when ``odom`` repeats the previous reading bit for bit (see module doc)."""
        o = check_pose3(odom, "odom")
        return self._last is not None and bool(np.array_equal(o, self._last))

    def hold(self, pose: np.ndarray) -> Prediction:
        """Prior for a scan with a stale reading: the last pose, weak (velocity) sigmas; the
        anchor stays where the reading was taken. The first scan that repeats the reading
        given to :meth:`reset` is the scan taken at the reset pose: its fit, not the reset
        pose, is where that reading was taken (a global fix confirmed on a scan: the next
        increment applies to the confirmed fit; anchoring it at the hypothesis instead left
        fr079 start 1714's track 0.3 m off inside a double wall).

        When the reset said how well its pose is known (``known``), that scan's prior is the
        reset pose with those sigmas, source ``"odometry"``: the pose is known as well as an
        odometry increment would tell it, and the scan refines it under that prior instead
        of deciding alone (a global fix that the drive's evidence found, confirmed on a scan
        of which the map explains little: see ``GlobalConfig.confirm_drive_prior``)."""
        self._settle(pose)
        at_reset, known = self._at_reset, self._known
        self._fresh = at_reset
        self._at_reset = False
        self._known = None
        if at_reset and known is not None:
            info = _information(float(pose[2]), known[0], known[0], known[1])
            return Prediction(
                pose=np.asarray(pose, dtype=np.float64).copy(),
                information=info,
                source="odometry",
                delta=np.zeros(3),
            )
        c = self.config
        info = _information(
            float(pose[2]), c.velocity_sigma_xy, c.velocity_sigma_xy, c.velocity_sigma_theta
        )
        return Prediction(
            pose=np.asarray(pose, dtype=np.float64).copy(), information=info, source="held"
        )

    def _settle(self, pose: np.ndarray) -> None:
        # ``pose`` is the outcome of the previous scan: if that scan brought a fresh reading,
        # it is where the reading was taken
        if self._fresh or self._anchor is None:
            self._anchor = np.asarray(pose, dtype=np.float64).copy()

    def increment(self, odom: np.ndarray) -> np.ndarray | None:
        """Robot-frame increment since the previous odometry pose (``None`` the first time);
        remembers ``odom``."""
        o = check_pose3(odom, "odom")
        delta = None if self._last is None else compose(invert(self._last), o)
        self._last = o
        return delta

    def predict(
        self,
        pose: np.ndarray,
        odom: np.ndarray | None,
        matched_from: np.ndarray | None = None,
        spread: np.ndarray | None = None,
    ) -> Prediction:
        if odom is None:
            raise LocalizationError("OdometryMotion.predict needs odometry")
        self._settle(pose)
        base = self._anchor if self._anchor is not None else pose
        # the scan fit measured this increment only if it starts from the reading it did
        matched = (
            matched_from is not None
            and self._last is not None
            and bool(np.array_equal(self._last, matched_from))
        )
        delta = self.increment(odom)
        self._fresh = True
        self._at_reset = False
        self._known = None
        c = self.config
        if delta is None:
            delta = np.zeros(3)
        s_trans, s_rot = odometry_sigmas(delta, c, matched)
        prior = compose(base, delta)
        info = _information(float(prior[2]), s_trans, s_trans, s_rot)
        if spread is not None:
            info[:2, :2] = _spread_information(float(base[2]), s_trans, spread)
        return Prediction(pose=prior, information=info, source="odometry", delta=delta)

    def accepted(self, previous: np.ndarray, pose: np.ndarray) -> None:
        return None

    def rejected(self) -> None:
        return None


class VelocityMotion:
    """Constant-velocity prior without odometry: the last pose moved by the smoothed
    translation per scan (capped at ``max_velocity``), heading kept; weak information."""

    def __init__(self, config: MotionConfig) -> None:
        self.config = config
        self._velocity = np.zeros(2)

    @property
    def velocity(self) -> np.ndarray:
        """Smoothed translation per scan (map frame, m)."""
        return self._velocity.copy()

    def reset(self) -> None:
        self._velocity = np.zeros(2)

    def set_velocity(self, velocity: np.ndarray) -> None:
        """Start from a known translation per scan (map frame, m), e.g. after a relocalisation."""
        v = np.asarray(velocity, dtype=np.float64).reshape(2)
        if not np.all(np.isfinite(v)):
            raise LocalizationError("velocity must be finite")
        self._velocity = v.copy()

    def predict(
        self,
        pose: np.ndarray,
        odom: np.ndarray | None = None,
        matched_from: np.ndarray | None = None,
    ) -> Prediction:
        c = self.config
        v = self._velocity if c.extrapolate else np.zeros(2)
        prior = np.array([pose[0] + v[0], pose[1] + v[1], pose[2]])
        info = _information(
            float(prior[2]), c.velocity_sigma_xy, c.velocity_sigma_xy, c.velocity_sigma_theta
        )
        return Prediction(pose=prior, information=info, source="velocity")

    def accepted(self, previous: np.ndarray, pose: np.ndarray) -> None:
        a = self.config.velocity_smoothing
        self._velocity = (1.0 - a) * self._velocity + a * (pose[:2] - previous[:2])
        vn = float(np.hypot(*self._velocity))
        if vn > self.config.max_velocity:
            self._velocity *= self.config.max_velocity / vn

    def rejected(self) -> None:
        self._velocity *= 0.5  # do not coast on while nothing confirms the motion


class Motion:
    """Per scan: :class:`OdometryMotion` when the scan carries ``odom`` (and
    ``config.use_odometry``), else :class:`VelocityMotion`. Implements :class:`MotionModel`."""

    def __init__(self, config: MotionConfig | None = None) -> None:
        self.config = config or MotionConfig()
        self.odometry = OdometryMotion(self.config)
        self.velocity = VelocityMotion(self.config)

    def reset(
        self, odom: np.ndarray | None = None, known: tuple[float, float] | None = None
    ) -> None:
        self.odometry.reset(odom if self.config.use_odometry else None, known)
        self.velocity.reset()

    def predict(
        self,
        pose: np.ndarray,
        odom: np.ndarray | None,
        matched_from: np.ndarray | None = None,
        spread: np.ndarray | None = None,
    ) -> Prediction:
        if odom is not None and self.config.use_odometry:
            if self.odometry.stale(odom):
                return self.odometry.hold(pose)
            return self.odometry.predict(pose, odom, matched_from, spread)
        if odom is not None:
            check_pose3(odom, "odom")  # same validation whether it is used or not
        self.odometry.reset()  # a gap in the odometry: the next increment starts afresh
        return self.velocity.predict(pose)

    def accepted(self, previous: np.ndarray, pose: np.ndarray) -> None:
        self.velocity.accepted(previous, pose)

    def rejected(self) -> None:
        self.velocity.rejected()
