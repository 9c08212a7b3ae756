"""Laser odometry: the motion between consecutive scans measured from the scans alone, given
to any localiser as its odometry when the robot sends none.

Why. With odometry the shape tracker, the relocalisation (hypotheses weighed over a drive need
the relative motion between scans) and the dead reckoning after a loss are at or near 100 % on
every map; without it (the seed paper's mode) they fall back on a constant-velocity guess with
weak sigmas, and on floor plans, where the missing furniture leaves little of a scan to match,
that is what fails. Two consecutive scans of the same laser see the same furniture and walls,
so they tell the motion far better than a floor plan does (the scan-to-scan fit of
:mod:`service.core.tracking.scan_odometry` already corrects a wheel odometry that way). What a
scan-only fit lacks is the initial guess wheel odometry provides: the robot of the paper's setup 2
turns 32 degrees between scans at the median and up to 90 at the 99th percentile, far beyond a
point-to-line fit's basin.

What. :class:`LaserOdometry` measures each scan's increment from the previous scan:

1. **Turn candidates** -- the scans' surface normals (oriented towards the laser) in a
   histogram of directions; a turn by ``t`` shifts the histogram by ``-t``, so the peaks of the
   circular cross-correlation of the two histograms are the turns the walls allow. Kept: the
   ``turn_candidates`` highest peaks within ``max_turn``, the last increment's turn (constant
   angular velocity) and no turn.
2. **Fit** -- from each candidate, with the translation of a constant velocity in the odometry
   frame (the last increment's translation turned by the last turn), the robust point-to-line
   fit of :func:`service.core.tracking.scan_odometry.match_increment` under a weak prior; the fit
   that explains most of the new scan wins. Along a direction the points do not observe (a
   corridor's axis) the fit keeps the constant-velocity guess.
3. **Verdict** -- the winner is *matched* when it explains at least ``min_inliers`` of the
   points and no fit from a different turn (or place) explains nearly as much
   (``ambiguity_margin``); else the increment is unknown.

:class:`LaserOdometryLocalizer` wraps any :class:`~service.core.types.Localizer`: a scan that
carries odometry goes to it unchanged (bit for bit while no scan lacked odometry); a scan
without odometry gets the laser odometry's pose, in one continuous odometry frame:

* a matched increment is composed onto the previous reading: the localiser sees an ordinary
  odometry stream (and checks it against the scans again, ``ShapeConfig.motion.scan_odometry``,
  which then marks it scan-matched: the turn terms leave its noise model), told that the
  reading was measured from the scans (``from_scans``: on a floor plan a pose the scan
  contradicts then counts towards ``lost`` though accepted, ``GlobalConfig.
  scan_odometry_violation``);
* a scan whose increment is unknown goes to the localiser without odometry, as the paper's
  mode sends every scan: the velocity prior, the scan decides (with the shape tracker's turn
  recovery), and a rejected scan counts towards ``lost`` at once, as a scan that does not
  match its predecessor (a kidnap) needs; an odometry reading would keep the odometry's
  tolerance of rejected scans. The next fresh reading starts the localiser's odometry afresh,
  and the wrapper's own frame stays continuous: its increment is the motion since the last
  fresh reading, the localiser's own estimates of the unmatched scans while it tracks (the motion
  prior from its recent motion), the constant-velocity guess while it searches, then the
  matched increment;
* a robot whose scans start or stop carrying odometry keeps one frame: the decision is per
  scan, and the wheel readings after laser ones are moved onto the laser odometry's frame at
  the switch (``odom`` of the first scan back composed onto the reading before it).

The paper's own mode (no synthetic odometry) is the localiser without this wrapper:
``create_localizer(..., laser_odometry=False)``.

Units: metres, radians; odometry poses ``[x, y, theta]`` in the odometry frame, increments in
the robot frame of the older scan.
"""

from __future__ import annotations

import dataclasses
import inspect
import math
from typing import Any

import numpy as np
from pydantic import ConfigDict, Field
from scipy.spatial import cKDTree

from service.core import numeric
from service.core.baselines import scan_points
from service.core.pose import compose, invert
from service.core.tracking.motion import ScanOdometryConfig, check_pose3
from service.core.tracking.scan_odometry import match_increment, surface_normals
from service.core.types import (
    Estimate,
    Localizer,
    LocalizerWrapper,
    Settings,
    check_scan,
    wrap_angle,
)

__all__ = [
    "LaserOdometry",
    "LaserOdometryConfig",
    "LaserOdometryLocalizer",
    "LaserStep",
    "config_for_kind",
    "observability",
    "turn_candidates",
    "with_laser_odometry",
]


class LaserOdometryConfig(Settings):
    """Parameters of :class:`LaserOdometry` (metres, radians)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    fit: ScanOdometryConfig = Field(
        default_factory=lambda: ScanOdometryConfig(min_constraint=0.01, normal_radius=0.5),
        description="The scan-to-scan fit (service.core.tracking.scan_odometry.match_increment): "
        "points, normals, gates, robust scale. min_constraint 0.01 instead of a wheel "
        "odometry check's 0.05: with no odometry the only other source along a weakly "
        "observed direction (a corridor with a few door jambs) is the constant-velocity "
        "guess, worse than a few points (tuning log intel, increments between corrected scans "
        "~17 apart: translation error p99 0.98 -> 0.39 m). normal_radius 0.5 instead of 0.2: "
        "along a corridor the walls ahead are what measure the motion, and a 1-degree laser's "
        "returns on them lie r * 0.017 m apart (0.17 m at 10 m): within 0.2 m they had no "
        "neighbours, hence no normal, and the increment along the axis was the guess, which "
        "then carries itself on (tuning log intel: a robot standing still for 130 scans was "
        "given 0.09 m per scan; 10-scan windows in corridors, translation error p90 0.90 -> "
        "0.22 m).",
    )
    histogram_bins: int = Field(
        180, ge=8, description="Bins of the surface-normal direction histogram over 2 pi."
    )
    turn_candidates: int = Field(
        4, ge=1, description="Highest peaks of the histograms' cross-correlation tried as turns."
    )
    max_turn: float = Field(
        2.1,
        gt=0,
        le=math.pi,
        description="Largest turn between two scans tried (rad): beyond, a 180-degree laser's "
        "two scans share too little to fit.",
    )
    prior_sigma_xy: float = Field(
        0.15, gt=0, description="Position sigma (m) of the fit's constant-velocity prior."
    )
    prior_sigma_theta: float = Field(
        0.3, gt=0, description="Heading sigma (rad) of the fit's prior about a candidate turn."
    )
    min_inliers: float = Field(
        0.3,
        gt=0,
        le=1,
        description="A fit explaining less than this share of the new scan's points (within "
        "fit.inlier_tolerance of the previous scan) leaves the increment unknown.",
    )
    ambiguity_margin: float = Field(
        0.05,
        ge=0,
        le=1,
        description="A fit from another candidate that ends more than 0.1 m or 0.1 rad away "
        "and explains within this share of the best leaves the increment unknown.",
    )
    speed_sigma: float = Field(
        0.1,
        gt=0,
        description="How much the translation per scan may change between two scans (m): a "
        "fit's rank is its explained share less half its squared deviation from the "
        "constant-velocity translation in these units (a place that looks alike after the "
        "wrong turn is reached only by a jump).",
    )
    max_deviation: float = Field(
        0.3,
        gt=0,
        description="A winning fit farther than this (m) from the constant-velocity "
        "translation leaves the increment unknown, unless it explains accept_share of the "
        "scan (a real log's scans can jump back and forth by 0.2 m: intel).",
    )
    min_overlap: float = Field(
        0.8,
        gt=0,
        description="Turns are tried up to the scan's field of view less this (rad), and at "
        "most max_turn: the two scans must share this much of their view.",
    )
    accept_share: float = Field(
        0.85,
        gt=0,
        le=1,
        description="A fit from the constant-velocity guess explaining at least this share "
        "wins without trying the other candidates (small motion: the common case at a "
        "scan rate of 10 Hz and more).",
    )
    observed_share: float = Field(
        0.05,
        gt=0,
        le=0.5,
        description="A direction of the position that less than this share of the matched "
        "points' weight observes (their normals' projection) is not measured: the increment "
        "there is the constant-velocity guess, and its noise model gets the guess's recent "
        "miss along it (LaserStep.spread).",
    )
    unobserved_unknown: bool = Field(
        True,
        description="An increment with a direction of the position its points do not observe "
        "(a corridor's axis: there it is the constant-velocity guess) is not given as "
        "odometry: the scan gets the localiser's weak hold prior, as an unknown increment "
        "does, and the map decides along that direction. Metric maps: on (their doors and "
        "furniture tell the position along a corridor: tuning log intel, robot stopping and "
        "starting in corridors, 97.4 -> 99.3 % of references within 0.5 m). Floor plans: off "
        "(a plan has only the walls; the guess is the better prior: tuning buildings 0-19, "
        "worst building 100 -> 95.4 % with it on).",
    )
    guess_sigma_initial: float = Field(
        0.05,
        gt=0,
        description="How far (m) the constant-velocity guess of the translation per scan is "
        "assumed to miss until fully measured scans tell (their miss's exponential mean "
        "square, guess_smoothing): a simulated robot at constant speed ~0.01 m, the tuning "
        "log intel's stop-and-go with scans out of order ~0.05-0.1 m.",
    )
    guess_sigma_floor: float = Field(
        0.01, gt=0, description="Smallest miss (m) the guess is credited with."
    )
    guess_smoothing: float = Field(
        0.05, gt=0, le=1, description="Weight of the newest miss in its mean square."
    )
    local_map_frames: int = Field(
        20,
        ge=0,
        description="A scan the previous one does not match is matched against the last "
        "this many keyframes (0 = off): a robot that turns more between two scans than its "
        "laser's field of view allows still sees walls it saw a few scans before.",
    )
    local_map_below: float = Field(
        0.5,
        ge=0,
        le=1,
        description="A match of the previous scan explaining less than this share is tried "
        "against the local map too; the local map's fit wins when it explains more.",
    )
    local_map_radius: float = Field(
        3.0, gt=0, description="Keyframes farther than this (m) leave the local map."
    )
    frame_distance: float = Field(
        0.1, gt=0, description="A matched scan becomes a keyframe once it moved this far (m) ..."
    )
    frame_turn: float = Field(0.3, gt=0, description="... or turned this much (rad).")
    max_velocity: float = Field(
        0.5, gt=0, description="Cap of the constant-velocity translation per scan (m)."
    )


def config_for_kind(kind: str) -> LaserOdometryConfig:
    """The laser odometry's defaults for a map ``kind`` (``metric`` | ``schematic``): the
    same but for ``unobserved_unknown`` (on for metric maps only)."""
    return LaserOdometryConfig(unobserved_unknown=kind != "schematic")


@dataclasses.dataclass(frozen=True)
class LaserStep:
    """One scan's increment: ``delta`` ``[dx, dy, dtheta]`` (robot frame of the previous
    scan; the constant-velocity guess when not ``matched``), whether the fit is trusted, the
    share of the new scan it explains and how many candidate fits ran."""

    delta: np.ndarray
    matched: bool
    explained: float
    fits: int
    #: Translation variance (2x2, m^2, the previous scan's frame) the fit could not remove:
    #: along a direction its points do not observe (a corridor's axis, where the increment is
    #: the constant-velocity guess) the guess's recent mean squared miss, zero elsewhere.
    spread: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((2, 2)))


def observability(
    ref_points: np.ndarray,
    ref_normals: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    delta: np.ndarray,
    config: ScanOdometryConfig,
) -> tuple[np.ndarray, float]:
    """The translation block (2x2) of the normal matrix of ``points`` (robot frame, unit
    ``normals``) moved by ``delta`` and paired with their nearest ``ref_points`` within
    ``config.gate_final`` whose normal agrees within ``normal_gate`` (Cauchy weights of the
    point-to-line residuals, ``robust_scale``), and the weights' sum: which directions of the
    position the pairs pin (the same quantity :func:`service.core.tracking.scan_odometry.observed`
    judges)."""
    if len(points) == 0 or len(ref_points) == 0:
        return np.zeros((2, 2)), 0.0
    c, s = math.cos(float(delta[2])), math.sin(float(delta[2]))
    q = np.column_stack(
        [
            c * points[:, 0] - s * points[:, 1] + delta[0],
            s * points[:, 0] + c * points[:, 1] + delta[1],
        ]
    )
    m = np.column_stack(
        [c * normals[:, 0] - s * normals[:, 1], s * normals[:, 0] + c * normals[:, 1]]
    )
    tree = cKDTree(ref_points)
    k = min(8, len(ref_points))
    dist, j = tree.query(q, k=k, distance_upper_bound=config.gate_final)
    dist = dist.reshape(len(q), k)
    j = np.minimum(j.reshape(len(q), k), len(ref_points) - 1)
    agree = np.abs(np.einsum("ikj,ij->ik", ref_normals[j], m)) >= math.cos(config.normal_gate)
    good = np.isfinite(dist) & agree
    first = np.argmax(good, axis=1)
    ok = good[np.arange(len(q)), first]
    if not np.any(ok):
        return np.zeros((2, 2)), 0.0
    jj = j[np.arange(len(q)), first][ok]
    nn = ref_normals[jj]
    r = np.einsum("ij,ij->i", nn, q[ok] - ref_points[jj])
    w = 1.0 / (1.0 + (r / config.robust_scale) ** 2)
    return numeric.matmul(nn.T * w, nn), float(w.sum())


def _oriented(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """``normals`` turned to face the laser (the origin)."""
    away = np.einsum("ij,ij->i", points, normals) > 0.0
    out = normals.copy()
    out[away] *= -1.0
    return out


def _histogram(points: np.ndarray, normals: np.ndarray, bins: int) -> np.ndarray:
    """Direction histogram of the oriented ``normals`` over 2 pi, each point weighted by its
    range (the beams' spacing on a surface grows with it: the weight is the surface length a
    point stands for), smoothed by a [1, 2, 1] kernel."""
    if len(points) == 0:
        return np.zeros(bins)
    phi = np.asarray(numeric.atan2(normals[:, 1], normals[:, 0]), dtype=np.float64)
    k = np.floor((phi + math.pi) * (bins / (2.0 * math.pi))).astype(np.intp) % bins
    w = np.hypot(points[:, 0], points[:, 1])
    h = np.bincount(k, weights=w, minlength=bins).astype(np.float64)
    return 2.0 * h + np.roll(h, 1) + np.roll(h, -1)


def turn_candidates(
    prev_hist: np.ndarray, hist: np.ndarray, count: int, max_turn: float
) -> list[float]:
    """The turns (rad, best first) at the ``count`` highest local maxima of the circular
    cross-correlation of two direction histograms (:func:`_histogram`) within ``max_turn``,
    each refined by a parabola through its neighbours. A wall whose normal lies at ``phi`` in
    the previous scan's frame lies at ``phi - t`` after a turn ``t``."""
    b = len(hist)
    if not np.any(prev_hist) or not np.any(hist):
        return []
    shifts = (np.arange(b)[:, None] + np.arange(b)[None, :]) % b
    # corr[s] = sum_j prev[j] * new[j - s]: new[(j - s) % b] = new[shifts[-s % b, j]]
    new_shifted = hist[shifts[(-np.arange(b)) % b]]
    corr = np.einsum("sj,j->s", new_shifted, prev_hist)
    left, right = np.roll(corr, 1), np.roll(corr, -1)
    peaks = np.flatnonzero((corr >= left) & (corr > right) & (corr > 0.0))
    peaks = peaks[np.argsort(-corr[peaks], kind="stable")]
    width = 2.0 * math.pi / b
    out: list[float] = []
    for s in peaks:
        den = left[s] - 2.0 * corr[s] + right[s]
        frac = 0.5 * (left[s] - right[s]) / den if den < 0.0 else 0.0
        t = float(wrap_angle(float((s + frac) * width)))
        if abs(t) <= max_turn:
            out.append(t)
        if len(out) >= count:
            break
    return out


class LaserOdometry:
    """Consecutive scans' increments (see the module docstring). ``step(ranges, angles)``
    returns the increment since the previous scan (``None`` on the first); ``keep`` only
    remembers a scan (one whose motion is known otherwise); ``reset()`` forgets the previous
    scan, the local map and the velocity. Picklable."""

    def __init__(self, config: LaserOdometryConfig | None = None) -> None:
        self.config = config or LaserOdometryConfig()
        self.reset()

    def reset(self) -> None:
        self._scan: tuple[np.ndarray, np.ndarray] | None = None  # the previous scan, raw
        self._surface_cache: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._last = np.zeros(3)  # the last increment (its turn and translation)
        self._pose = np.zeros(3)  # the previous scan's pose in this odometry's own frame
        self._before = np.zeros(3)  # the pose of the scan before it
        #: Keyframes of the local map: (pose, points, normals) of matched scans, oldest first.
        self._frames: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._frame_last = False  # the previous scan is the last keyframe
        #: Mean squared miss (m^2) of the constant-velocity guess on fully measured scans.
        self._guess_var = self.config.guess_sigma_initial**2

    @property
    def has_previous(self) -> bool:
        """Whether a previous scan is kept (the next :meth:`step` returns an increment)."""
        return self._scan is not None

    def guess(self) -> np.ndarray:
        """The constant-velocity increment: the last increment's translation turned by its
        turn (the same translation in the odometry frame), capped at ``max_velocity``; the
        last turn."""
        last = self._last
        c, s = math.cos(float(last[2])), math.sin(float(last[2]))
        t = np.array([c * last[0] + s * last[1], -s * last[0] + c * last[1]])
        n = math.hypot(float(t[0]), float(t[1]))
        if n > self.config.max_velocity:
            t *= self.config.max_velocity / n
        return np.array([t[0], t[1], float(last[2])])

    def remember(self, delta: np.ndarray) -> None:
        """Take ``delta`` as the last increment, the motion from the scan before the previous
        one to the previous one (known otherwise than by :meth:`step`: a localiser's
        estimates, a wheel odometry): the velocity of the next guess."""
        d = np.asarray(delta, dtype=np.float64).reshape(3)
        if np.all(np.isfinite(d)):
            self._last = d.copy()
            self._pose = compose(self._before, d)

    def keep(self, ranges: np.ndarray, angles: np.ndarray, delta: np.ndarray | None) -> None:
        """Remember this scan as the previous one, its increment ``delta`` known otherwise
        (a wheel odometry's; ``None``: unknown, the velocity is forgotten). Costs nothing
        until a :meth:`step` needs the scan; the local map starts afresh."""
        self._scan = (ranges, angles)
        self._surface_cache = None
        self._frames = []
        self._frame_last = False
        self._before = self._pose.copy()
        if delta is None:
            self._last = np.zeros(3)
        else:
            self.remember(delta)

    def _surface(
        self, ranges: np.ndarray, angles: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The scan's points with a surface normal (robot frame), their normals facing the
        laser and the direction histogram."""
        f = self.config.fit
        pts = scan_points(ranges, angles, f.max_range)
        nrm = surface_normals(pts, f.normal_window, f.normal_radius, f.max_flatness)
        ok = np.all(np.isfinite(nrm), axis=1)
        pts = np.ascontiguousarray(pts[ok])
        nrm = np.ascontiguousarray(_oriented(pts, nrm[ok]))
        return pts, nrm, _histogram(pts, nrm, self.config.histogram_bins)

    def _previous(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if self._scan is None:
            return None
        if self._surface_cache is None:
            self._surface_cache = self._surface(*self._scan)
        return self._surface_cache

    def _local_map(self) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The keyframes' points and normals in the previous scan's frame, with their
        direction histogram (``None`` when it holds nothing beyond the previous scan)."""
        if not self._frames or (len(self._frames) == 1 and self._frame_last):
            return None
        back = invert(self._pose)
        pts, nrm = [], []
        for pose, p, n in self._frames:
            rel = compose(back, pose)
            c, s = math.cos(float(rel[2])), math.sin(float(rel[2]))
            R = np.array([[c, -s], [s, c]])
            pts.append(numeric.matmul(p, R.T) + rel[:2])
            nrm.append(numeric.matmul(n, R.T))
        P = np.ascontiguousarray(np.vstack(pts))
        N = np.ascontiguousarray(np.vstack(nrm))
        w = np.hypot(P[:, 0], P[:, 1])
        b = self.config.histogram_bins
        phi = np.asarray(numeric.atan2(N[:, 1], N[:, 0]), dtype=np.float64)
        k = np.floor((phi + math.pi) * (b / (2.0 * math.pi))).astype(np.intp) % b
        h = np.bincount(k, weights=w, minlength=b).astype(np.float64)
        return P, N, 2.0 * h + np.roll(h, 1) + np.roll(h, -1)

    def _match(
        self,
        ref: tuple[np.ndarray, np.ndarray, np.ndarray],
        cur: tuple[np.ndarray, np.ndarray, np.ndarray],
        guess: np.ndarray,
        widest: float,
    ) -> tuple[bool, float, np.ndarray, int, np.ndarray]:
        """The candidate fits of ``cur`` (points, normals, histogram; robot frame) to
        ``ref`` (the previous scan's frame) from ``guess`` and the turns the histograms allow
        within ``widest``: (matched, share, increment, fits, spread) of the best ranked
        (spread: :attr:`LaserStep.spread`)."""
        cfg = self.config
        ref_pts, ref_nrm, ref_hist = ref
        pts, nrm, hist = cur
        stride = max(1, len(pts) // cfg.fit.max_points)
        p, n = pts[::stride], nrm[::stride]
        sxy, sth = cfg.prior_sigma_xy, cfg.prior_sigma_theta
        info = np.diag([1.0 / sxy**2, 1.0 / sxy**2, 1.0 / sth**2])
        fits: list[tuple[float, np.ndarray]] = []

        def run(turn: float) -> float:
            start = np.array([guess[0], guess[1], turn])
            fit, share = match_increment(ref_pts, ref_nrm, p, n, start, info, cfg.fit)
            ok = bool(np.all(np.isfinite(fit)))
            if ok:
                fit[2] = wrap_angle(float(fit[2]))
            fits.append((share if ok else 0.0, fit if ok else start))
            return fits[-1][0]

        def rank(k: int) -> float:
            share, fit = fits[k]
            dev = math.hypot(float(fit[0] - guess[0]), float(fit[1] - guess[1]))
            return share - 0.5 * (max(0.0, dev - cfg.speed_sigma) / cfg.speed_sigma) ** 2

        tried = [float(guess[2])]
        if run(tried[0]) < cfg.accept_share:
            more = turn_candidates(ref_hist, hist, cfg.turn_candidates, widest)
            for t in [*more, 0.0]:
                if all(abs(float(wrap_angle(t - u))) > 0.05 for u in tried):
                    tried.append(t)
                    run(t)
        ranks = [rank(k) for k in range(len(fits))]
        order = sorted(range(len(fits)), key=lambda k: (-ranks[k], k))
        share, best = fits[order[0]]
        dev = math.hypot(float(best[0] - guess[0]), float(best[1] - guess[1]))
        matched = share >= cfg.min_inliers and (
            dev <= cfg.max_deviation or share >= cfg.accept_share
        )
        for k in order[1:]:
            other = fits[k][1]
            far = math.hypot(float(other[0] - best[0]), float(other[1] - best[1])) > 0.1
            far = far or abs(float(wrap_angle(float(other[2] - best[2])))) > 0.1
            if far and ranks[k] >= ranks[order[0]] - cfg.ambiguity_margin:
                matched = False
        spread = np.zeros((2, 2))
        if matched:
            normal, total = observability(ref_pts, ref_nrm, p, n, best, cfg.fit)
            vals, vecs = numeric.eigh_sym2(normal)
            for k in range(2):
                if total <= 0.0 or vals[k] < cfg.observed_share * total:
                    spread += self._guess_var * np.outer(vecs[:, k], vecs[:, k])
        return matched, float(share), best, len(fits), spread

    def step(self, ranges: np.ndarray, angles: np.ndarray) -> LaserStep | None:
        """The increment of this scan since the previous one (``None`` on the first scan
        after a reset); the scan becomes the previous one."""
        cfg = self.config
        prev = self._previous()
        cur = self._surface(ranges, angles)
        self._scan = (ranges, angles)
        self._surface_cache = cur
        self._before = self._pose.copy()
        self._frame_last = False
        if prev is None:
            self._frames = [(self._pose.copy(), cur[0], cur[1])]
            self._frame_last = True
            return None
        guess = self.guess()
        if len(cur[0]) < 10 or len(prev[0]) < 10:
            return self._unmatched(guess, 0.0, 0)
        span = float(np.max(angles) - np.min(angles))
        widest = min(cfg.max_turn, max(0.0, span - cfg.min_overlap))
        matched, share, best, fits, spread = self._match(prev, cur, guess, widest)
        partial = cfg.unobserved_unknown and bool(np.any(spread))
        if (not matched or partial or share < cfg.local_map_below) and cfg.local_map_frames > 0:
            local = self._local_map()
            if local is not None:
                m2, s2, b2, f2, sp2 = self._match(local, cur, guess, math.pi)
                fits += f2
                better = not matched or s2 > share or (partial and not np.any(sp2))
                if m2 and better:
                    matched, share, best, spread = True, s2, b2, sp2
        if matched and cfg.unobserved_unknown and np.any(spread):
            # part of the motion is the guess: not a measurement to give as odometry
            self._pose = compose(self._before, best)
            return LaserStep(best.copy(), False, share, fits, spread)
        if not matched:
            return self._unmatched(guess, share, fits)
        if not np.any(spread):
            # fully measured: how far the constant-velocity guess was off
            miss = float((best[0] - guess[0]) ** 2 + (best[1] - guess[1]) ** 2)
            a = cfg.guess_smoothing
            self._guess_var = max((1.0 - a) * self._guess_var + a * miss, cfg.guess_sigma_floor**2)
        self._last = best.copy()
        self._pose = compose(self._before, best)
        self._add_frame(cur[0], cur[1])
        return LaserStep(best.copy(), True, share, fits, spread)

    def _unmatched(self, guess: np.ndarray, share: float, fits: int) -> LaserStep:
        """An unknown increment: the guess stands in (until :meth:`remember`). The scan does
        not join the local map (its pose is not measured); the next scan is matched against
        it and, if that fails, against the keyframes, which then also correct the motion
        assumed for this one."""
        self._pose = compose(self._before, guess)
        return LaserStep(guess.copy(), False, share, fits)

    def _add_frame(self, pts: np.ndarray, nrm: np.ndarray) -> None:
        """This scan becomes a keyframe when it moved ``frame_distance`` or turned
        ``frame_turn`` from the last one; keyframes beyond ``local_map_radius`` of it or
        more than ``local_map_frames`` go."""
        cfg = self.config
        last = self._frames[-1][0] if self._frames else None
        if last is not None:
            rel = compose(invert(last), self._pose)
            moved = math.hypot(float(rel[0]), float(rel[1]))
            if moved < cfg.frame_distance and abs(float(rel[2])) < cfg.frame_turn:
                return
        self._frames.append((self._pose.copy(), pts, nrm))
        self._frame_last = True
        here = self._pose
        self._frames = [
            f
            for f in self._frames[-cfg.local_map_frames :]
            if math.hypot(float(f[0][0] - here[0]), float(f[0][1] - here[1]))
            <= cfg.local_map_radius
        ]


class LaserOdometryLocalizer(LocalizerWrapper):
    """A localiser fed the laser odometry on scans that carry no odometry (module docstring).

    Wraps ``inner`` (any :class:`~service.core.types.Localizer`); :attr:`pose`, ``method``
    and everything else are the inner localiser's, read and set on it (``loc.gconfig = ...``
    changes the inner localiser's), except the wrapper's own attributes (``_OWN``).
    ``reset(initial_pose, odom)`` forgets the previous scan (the robot may have been moved).
    Picklable when the inner localiser is.
    """

    def __init__(self, inner: Localizer, config: LaserOdometryConfig | None = None) -> None:
        super().__init__(inner)
        #: ``None``: the defaults of the inner localiser's map kind (:func:`config_for_kind`).
        #: Not ``config``: that name reads the inner localiser's own configuration.
        self.laser_config = config
        self._kind = str(inner.map_data.kind)
        self.odometry = LaserOdometry(config or config_for_kind(self._kind))
        #: the inner localiser takes an increment's extra variance (``odom_spread``)
        params = inspect.signature(inner.update).parameters
        self._spreads = "odom_spread" in params
        #: the inner localiser takes the word that a reading was measured from the scans
        self._from_scans = "from_scans" in params
        self._reading: np.ndarray | None = None  # the odometry pose last given to ``inner``
        self._fresh: np.ndarray | None = None  # the last one that was not a repeat
        #: Wheel readings given as ``frame (+) odom``; ``None`` until a scan without odometry
        #: came before one with it (until then they pass bit for bit).
        self._frame: np.ndarray | None = None
        self._wheel: np.ndarray | None = None  # the previous scan's wheel reading, as received
        self._pending = np.zeros(3)  # motion over unmatched scans since ``_fresh``
        self._last_pose: np.ndarray | None = None  # the inner's estimate of the last scan
        self._last_status = ""
        #: The last scan's laser increment (``None``: none, e.g. the scan carried odometry).
        self.last_step: LaserStep | None = None

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Restart the inner localiser at ``initial_pose`` (``None``: global localisation)
        with the robot's odometry pose ``odom`` there, if it sends one."""
        o = None if odom is None else check_pose3(odom, "odom")
        self.inner.reset(initial_pose, odom)
        self.odometry.reset()
        self._frame = None
        self._wheel = None if odom is None else np.asarray(odom, dtype=np.float64).copy()
        self._reading = o
        self._fresh = o
        self._pending = np.zeros(3)
        self._last_pose = None
        self._last_status = ""
        self.last_step = None

    def update(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None = None
    ) -> Estimate:
        """Localise one scan: with the robot's odometry pose ``odom`` when it sends one, else
        with the laser odometry's (see the class docstring)."""
        r, a = check_scan(ranges, angles)
        kind = str(self.inner.map_data.kind)
        if self.laser_config is None and kind != self._kind:  # a map of the other kind now
            self._kind = kind
            self.odometry.config = config_for_kind(kind)
        spread = None
        kw: dict[str, Any] = {}
        if odom is None:
            reading = self._laser_reading(r, a)
            self._wheel = None
            step = self.last_step
            if step is not None and not step.matched:
                # No measured motion: the scan goes to the localiser as the paper's mode sends
                # it, without odometry. A repeated reading would keep the odometry's tolerance
                # of rejected scans, and a scan that does not match its predecessor is what a
                # kidnap looks like: the tracker then accepted the new place's scans at the
                # old pose (10.6 m off, 32 % explained) for two scans before going lost.
                reading = None
            elif step is not None and np.any(step.spread) and self._spreads:
                spread = step.spread
            if reading is not None and self._from_scans:
                kw["from_scans"] = True
        else:
            reading = self._wheel_reading(r, a, odom)
        if spread is not None:
            kw["odom_spread"] = spread
        est = self.inner.update(r, a, reading, **kw)
        self._after(est)
        return est

    def _wheel_reading(self, r: np.ndarray, a: np.ndarray, odom: np.ndarray) -> np.ndarray:
        """The reading of a scan that carries the robot's odometry: as received while no
        scan lacked it; else moved onto the laser odometry's frame, continuous at the switch."""
        o = check_pose3(odom, "odom")
        self.last_step = None
        if self._wheel is None and self._reading is not None:
            # back after laser readings: the laser odometry measures this scan's increment,
            # the wheel readings continue from there
            stepped = self._laser_reading(r, a)
            self._frame = compose(stepped, invert(o))
        else:
            delta = None if self._wheel is None else compose(invert(self._wheel), o)
            self.odometry.keep(r, a, delta)
        self._wheel = np.asarray(odom, dtype=np.float64).copy()
        out = np.asarray(odom, dtype=np.float64) if self._frame is None else compose(self._frame, o)
        self._reading = check_pose3(out, "odom")
        self._fresh = self._reading.copy()
        self._pending = np.zeros(3)
        return out

    def _laser_reading(self, r: np.ndarray, a: np.ndarray) -> np.ndarray:
        """The laser odometry's reading of this scan (module docstring): the previous fresh
        reading moved by the motion since, or the previous reading repeated when this scan's
        increment is unknown."""
        step = self.odometry.step(r, a)
        self.last_step = step
        if self._reading is None or self._fresh is None:
            self._reading = np.zeros(3)  # the first reading: the odometry frame starts here
            self._fresh = self._reading.copy()
            self._pending = np.zeros(3)
            return self._reading.copy()
        if step is None or not step.matched:
            return self._reading.copy()  # kept for the frame; the localiser gets no odometry
        out = compose(compose(self._fresh, self._pending), step.delta)
        self._pending = np.zeros(3)
        self._reading = out.copy()
        self._fresh = out.copy()
        return out

    def _after(self, est: Estimate) -> None:
        """Account the motion of an unmatched scan towards the next fresh reading: the inner
        localiser's own estimate while it tracks, else the constant-velocity guess."""
        pose = np.asarray(est.pose, dtype=np.float64).copy()
        step = self.last_step
        if step is not None and not step.matched:
            tracked = est.status == "tracking" and self._last_status == "tracking"
            if tracked and self._last_pose is not None:
                d = compose(invert(self._last_pose), pose)
            else:
                d = step.delta
            self._pending = compose(self._pending, d)
            self.odometry.remember(d)
        self._last_pose = pose
        self._last_status = est.status

    def __setattr__(self, name: str, value: Any) -> None:
        # an attribute read from the inner localiser is set there too: else a caller tuning
        # it (a benchmark's ablation, a test) would change a shadow copy the scans never use
        inner = self.__dict__.get("inner")
        if (
            inner is not None
            and name not in _OWN
            and not hasattr(type(self), name)
            and hasattr(inner, name)
        ):
            setattr(inner, name, value)
        else:
            object.__setattr__(self, name, value)


#: The attributes :class:`LaserOdometryLocalizer` keeps for itself (everything else it reads
#: and sets on the inner localiser).
_OWN = frozenset(
    {
        "inner",
        "laser_config",
        "odometry",
        "last_step",
        "_kind",
        "_spreads",
        "_from_scans",
        "_reading",
        "_fresh",
        "_frame",
        "_wheel",
        "_pending",
        "_last_pose",
        "_last_status",
    }
)


def with_laser_odometry(
    loc: Localizer, enabled: bool = True, config: LaserOdometryConfig | None = None
) -> Localizer:
    """``loc`` fed the laser odometry on scans without odometry when ``enabled``; ``loc``
    itself otherwise (the paper's mode: nothing synthetic)."""
    if not enabled:
        return loc
    return LaserOdometryLocalizer(loc, config)  # type: ignore[return-value]
