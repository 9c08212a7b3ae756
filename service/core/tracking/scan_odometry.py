"""Odometry checked against the scans: each odometry increment is corrected by matching the
new scan to the previous one, with the increment as the prior.

Why. A wheel odometry can be wrong in ways its noise model does not cover. The tuning log
fr079's odometry never moves backwards: where the robot backs up (104 of 4 728 consecutive
referenced scan pairs) it reports the same distance *forwards*, so the motion prior is off by
twice the step, and a tracker or a kept hypothesis slides along a corridor of a floor plan,
whose missing furniture leaves the scan too little to resist. Two consecutive scans of the
same laser see the same furniture, so they tell the motion far better than a floor plan does:
on fr079, matched from the odometry's increment, the translation error against the reference
at the 99th percentile is 0.10 m instead of the odometry's 0.18 m, the heading error at the
90th 1.2 degrees instead of 2.7 (``bench/bench_odometry.py``).

What. :class:`ScanOdometry` keeps the previous scan (points and surface normals, robot frame)
and turns each odometry reading into a corrected one, in the odometry's own frame: the
increment since the previous reading is refined by a robust point-to-line fit of the new
scan's points to the previous scan, with the increment as the motion prior
(``MotionConfig``'s noise model: in a corridor the direction the scans cannot observe keeps
the odometry's value). The fit is kept when it explains at least ``min_inliers`` of the
points; else the raw increment is. The corrected increment is composed onto the previous
corrected reading, so everything downstream (the motion model, the search's hypotheses and
keyframes) sees a corrected odometry stream and nothing else changes. A reading repeated bit
for bit (a stale odometry, :mod:`service.core.tracking.motion`) is passed on repeated, and the next
fresh one is matched against the scan of the last fresh one.

Units: metres, radians; odometry poses ``[x, y, theta]`` in the odometry frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from service.core import kernels, numeric
from service.core.baselines import scan_points
from service.core.kernels import grid as grid_kernels
from service.core.kernels import odometry as odometry_kernels
from service.core.pose import compose, invert, transform_points
from service.core.tracking.motion import MotionConfig, ScanOdometryConfig, odometry_sigmas
from service.core.types import wrap_angle


def surface_normals(
    points: np.ndarray, half_window: int, radius: float, max_flatness: float
) -> np.ndarray:
    """Unit surface normals ``(n, 2)`` of beam-ordered points (robot frame) by a principal
    component fit of each point's neighbours: the points within ``half_window`` beams and
    ``radius`` metres of it. NaN where fewer than 3 points qualify or where they do not lie
    on a line (the smaller spread over the larger above ``max_flatness``: a corner).

    Not the chord of the two neighbours (:func:`service.core.sensor.refine.scan_normals`): a laser's
    neighbouring returns at 1 m lie ~1 cm apart, as far as its range noise, and a chord's
    normal then swings by tens of degrees; a scan-to-scan fit whose pairs pull along such
    normals slides along a corridor (generated building 12, a corridor at 1.1 m: 0.1 m too
    far per 0.1 m step)."""
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 2))
    if kernels.HAVE_NUMBA:
        return odometry_kernels.surface_normals(
            p, int(half_window), float(radius), float(max_flatness)
        )
    n = len(p)
    out = np.full((n, 2), np.nan)
    if n < 3:
        return out
    h = max(1, int(half_window))
    idx = np.arange(n)[:, None] + np.arange(-h, h + 1)[None, :]
    valid = (idx >= 0) & (idx < n)
    nb = p[np.clip(idx, 0, n - 1)]  # (n, 2h+1, 2)
    d = nb - p[:, None, :]
    valid &= np.einsum("ijk,ijk->ij", d, d) <= radius * radius
    cnt = valid.sum(axis=1)
    w = valid.astype(np.float64)
    mean = np.einsum("ij,ijk->ik", w, nb) / np.maximum(cnt, 1)[:, None]
    c = nb - mean[:, None, :]
    sxx = np.einsum("ij,ij->i", w, c[:, :, 0] ** 2)
    syy = np.einsum("ij,ij->i", w, c[:, :, 1] ** 2)
    sxy = np.einsum("ij,ij->i", w, c[:, :, 0] * c[:, :, 1])
    # eigenvalues of [[sxx, sxy], [sxy, syy]]; the normal is the smaller one's eigenvector
    half = 0.5 * (sxx + syy)
    root = np.sqrt(np.maximum(0.25 * (sxx - syy) ** 2 + sxy**2, 0.0))
    small, large = half - root, half + root
    angle = 0.5 * numeric.atan2(2.0 * sxy, sxx - syy)  # direction of the larger spread
    ok = (cnt >= 3) & (large > 0) & (small <= max_flatness * large)
    out[ok, 0] = -np.sin(angle[ok])
    out[ok, 1] = np.cos(angle[ok])
    return out


def _surface_points(
    ranges: np.ndarray, angles: np.ndarray, config: ScanOdometryConfig
) -> tuple[np.ndarray, np.ndarray]:
    """The returns within ``max_range`` that have a surface normal
    (:func:`surface_normals`), robot frame, and their normals."""
    pts = scan_points(ranges, angles, config.max_range)
    nrm = surface_normals(pts, config.normal_window, config.normal_radius, config.max_flatness)
    ok = np.all(np.isfinite(nrm), axis=1)
    return np.ascontiguousarray(pts[ok]), np.ascontiguousarray(nrm[ok])


def _prior_information(delta: np.ndarray, motion: MotionConfig) -> np.ndarray:
    """The odometry model's information of one increment (robot frame of the older scan)."""
    s_trans, s_rot = odometry_sigmas(delta, motion)
    return np.diag([1.0 / s_trans**2, 1.0 / s_trans**2, 1.0 / s_rot**2])


def match_increment(
    prev_points: np.ndarray,
    prev_normals: np.ndarray,
    points: np.ndarray,
    normals: np.ndarray,
    delta: np.ndarray,
    information: np.ndarray,
    config: ScanOdometryConfig,
) -> tuple[np.ndarray, float]:
    """Refine the increment ``delta`` (pose of the new scan in the previous scan's frame) by
    a robust point-to-line fit of ``points`` ``(n, 2)`` (new scan, robot frame) to
    ``prev_points`` with their unit ``prev_normals``, plus the prior ``information`` (3x3) on
    ``delta``: Gauss-Newton, each point (unit surface ``normals``, robot frame) associated
    with the nearest previous point within a gate shrinking from ``gate_initial`` to
    ``gate_final`` whose normal agrees with the point's within ``normal_gate``, Cauchy
    weights, the points counted as at most ``effective_points`` against the prior. The fit
    moves the increment's position only along directions the points observe
    (:func:`observed`). Returns the increment and the share of ``points`` within
    ``inlier_tolerance`` of the previous scan's surfaces."""
    d0 = np.asarray(delta, dtype=np.float64).reshape(3).copy()
    if len(points) == 0 or len(prev_points) == 0:
        return d0, 0.0
    if kernels.HAVE_NUMBA:
        cell = max(config.gate_initial, config.gate_final)
        ox, oy, nx, ny, start, items = grid_kernels.grid_build(prev_points, cell)
        x, share, normal, total = odometry_kernels.match_iterations(
            prev_points,
            prev_normals,
            start,
            items,
            ox,
            oy,
            nx,
            ny,
            cell,
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(normals, dtype=np.float64),
            d0.copy(),
            np.ascontiguousarray(information, dtype=np.float64),
            math.cos(config.normal_gate),
            int(config.iterations),
            float(config.gate_initial),
            float(config.gate_final),
            float(config.robust_scale),
            1.0 / config.point_sigma**2,
            float(config.effective_points),
            float(config.inlier_tolerance),
        )
    else:
        x, share, normal, total = _match_numpy(
            prev_points,
            prev_normals,
            cKDTree(prev_points),
            points,
            normals,
            d0,
            information,
            config,
        )
    return observed(d0, np.asarray(x), np.asarray(normal), float(total), config), float(share)


def observed(
    delta: np.ndarray, fit: np.ndarray, normal: np.ndarray, total: float, config: ScanOdometryConfig
) -> np.ndarray:
    """The fitted increment with its position correction kept only along the directions
    the points observe: an eigen-direction of the points' normal matrix (translation block,
    robust weights ``normal`` summing to ``total``) holding less than ``min_constraint`` of
    the weight keeps the odometry's value (the heading correction is kept whole).

    Why: along a corridor only a few returns (a door jamb, the far end) pin the position, and
    the fit then follows their small biases instead of the odometry (generated building 12:
    0.07 m too far along a corridor on a 0.1 m step with 3 of 237 points across the axis)."""
    out = np.asarray(fit, dtype=np.float64).copy()
    if total <= 0:
        return np.asarray(delta, dtype=np.float64).copy()
    vals, vecs = numeric.eigh_sym2(normal[:2, :2])
    corr = out[:2] - delta[:2]
    keep = np.zeros(2)
    for k in range(2):
        if vals[k] >= config.min_constraint * total:
            keep += numeric.dot(vecs[:, k], corr) * vecs[:, k]
    out[:2] = delta[:2] + keep
    return out


def _match_numpy(
    prev_points: np.ndarray,
    prev_normals: np.ndarray,
    tree: cKDTree,
    points: np.ndarray,
    normals: np.ndarray,
    delta: np.ndarray,
    information: np.ndarray,
    config: ScanOdometryConfig,
) -> tuple[np.ndarray, float, np.ndarray, float]:
    """The numpy reference of :func:`service.core.kernels.odometry.match_iterations`
    (``tree`` a KD-tree of ``prev_points``)."""
    x = np.asarray(delta, dtype=np.float64).copy()
    x0 = x.copy()
    n = len(points)
    cos_gate = math.cos(config.normal_gate)

    def associate(gate: float) -> tuple[np.ndarray, np.ndarray]:
        # the nearest previous point within the gate whose normal agrees (of the 16 nearest)
        q = transform_points(x, points)
        m = numeric.matmul(
            normals,
            np.array([[math.cos(x[2]), math.sin(x[2])], [-math.sin(x[2]), math.cos(x[2])]]),
        )
        dist, j = tree.query(q, k=min(16, len(prev_points)), distance_upper_bound=gate)
        dist = dist.reshape(len(q), -1)
        j = j.reshape(len(q), -1)
        jj = np.minimum(j, len(prev_points) - 1)
        agree = np.abs(np.einsum("ikj,ij->ik", prev_normals[jj], m)) >= cos_gate
        good = np.isfinite(dist) & agree
        first = np.argmax(good, axis=1)
        ok = good[np.arange(len(q)), first]
        return q, np.where(ok, j[np.arange(len(q)), first], -1)

    its = max(1, int(config.iterations))
    for k in range(its):
        gate = config.gate_initial + (config.gate_final - config.gate_initial) * k / max(1, its - 1)
        q, j = associate(gate)
        ok = j >= 0
        if not np.any(ok):
            return x, 0.0, np.zeros((3, 3)), 0.0
        nn = prev_normals[j[ok]]
        qq = q[ok]
        r = np.einsum("ij,ij->i", nn, qq - prev_points[j[ok]])
        rq = qq - x[:2]  # the rotated new points, about the new scan's origin
        jac = np.column_stack([nn[:, 0], nn[:, 1], nn[:, 1] * rq[:, 0] - nn[:, 0] * rq[:, 1]])
        w = 1.0 / (1.0 + (r / config.robust_scale) ** 2)
        total = float(w.sum())
        scale = 1.0 / config.point_sigma**2
        if total > config.effective_points:
            scale *= config.effective_points / total
        normal = numeric.matmul(jac.T * w, jac)
        H = scale * normal + information
        e = x - x0
        e[2] = wrap_angle(float(e[2]))
        g = scale * numeric.matvec(jac.T * w, r) + numeric.matvec(information, e)
        try:
            step = numeric.solve(H, -g)
        except np.linalg.LinAlgError:
            break
        x = x + step
        if float(np.hypot(step[0], step[1])) < 1e-4 and abs(float(step[2])) < 1e-5:
            break
    q, j = associate(config.gate_final)
    ok = j >= 0
    if not np.any(ok):
        return x, 0.0, normal, total
    r = np.abs(np.einsum("ij,ij->i", prev_normals[j[ok]], q[ok] - prev_points[j[ok]]))
    return x, float(np.sum(r <= config.inlier_tolerance)) / n, normal, total


class ScanOdometry:
    """Corrects an odometry stream with the scans (see the module docstring).

    ``correct(ranges, angles, odom)`` returns the corrected odometry pose for the scan;
    ``reset(odom)`` re-anchors it: the corrected frame equals the raw one at ``odom`` and the
    previous scan is forgotten. Picklable.
    """

    #: the turn (rad) the last fit took out of its raw increment (0: none); a class default,
    #: so a state pickled before it was kept loads
    owed: float = 0.0

    def __init__(self, config: ScanOdometryConfig, motion: MotionConfig) -> None:
        self.config = config
        self.motion = motion
        self._raw: np.ndarray | None = None  # last fresh raw reading
        self._out: np.ndarray | None = None  # its corrected reading
        self._points: np.ndarray | None = None  # the scan of the last fresh reading
        self._normals: np.ndarray | None = None
        #: share of the points the last fit explained (NaN: no fit on the last reading)
        self.explained = math.nan
        #: the corrected reading the last reading's increment was measured from by the fit
        #: (``None``: the increment was not replaced); a motion model passed it knows its
        #: increment from there is scan-matched (``MotionConfig.matched_turn_noise``)
        self.matched_from: np.ndarray | None = None
        self.owed = 0.0

    @property
    def corrected(self) -> bool:
        """Whether the last reading's increment was replaced by the fit."""
        return self.matched_from is not None

    def reset(self, odom: np.ndarray | None = None) -> None:
        self._raw = None if odom is None else np.asarray(odom, dtype=np.float64).copy()
        self._out = None if odom is None else self._raw.copy()
        self._points = self._normals = None
        self.owed = 0.0

    def _fallback(
        self,
        pts: np.ndarray,
        nrm: np.ndarray,
        delta: np.ndarray,
        fit: np.ndarray,
        share: float,
    ) -> tuple[np.ndarray, float]:
        """``ScanOdometryConfig.fallback_sigma``: the scan fitted again from no translation
        (``delta``'s turn kept, its sigma as the odometry model gives it) under a weak
        position prior; that fit when it explains at least ``min_inliers`` of the points and
        ``fallback_gain`` more than ``fit`` did (``share``), else ``fit``. On the tuning log
        fr079 fed every 3rd scan it corrects 11 of the 14 increments that stayed more than
        0.2 m off (the robot backing up while the odometry counts forward: the odometry's
        increment is 0.6 m from the truth, beyond the association gate); fed every scan it
        changes nothing there; on intel it replaces one increment, the second half of a
        0.7 m back-and-forth jump of the odometry, which then no longer cancels (one
        reference pair 5 cm worse)."""
        s_trans, s_rot = odometry_sigmas(delta, self.motion)
        sigma = max(self.config.fallback_sigma, s_trans)
        start = np.array([0.0, 0.0, float(delta[2])])
        info = np.diag([1.0 / sigma**2, 1.0 / sigma**2, 1.0 / s_rot**2])
        assert self._points is not None and self._normals is not None
        again, s2 = match_increment(self._points, self._normals, pts, nrm, start, info, self.config)
        gain = s2 - share
        if (
            s2 >= self.config.min_inliers
            and gain >= self.config.fallback_gain
            and np.all(np.isfinite(again))
        ):
            return again, s2
        return fit, share

    def _deferred(
        self, pts: np.ndarray, nrm: np.ndarray, delta: np.ndarray, fit: np.ndarray, share: float
    ) -> tuple[np.ndarray, float]:
        """The scan fitted again from ``delta`` turned by the turn the last fit took out of
        its increment (:attr:`owed`); that fit if it explains ``min_inliers``, else ``fit``.

        Why: an odometry can stamp a turn one scan early. The scans then take the turn out
        of that increment and see it in the next, whose raw increment lacks it: from there
        the fit starts outside its association gate and fails, and the raw increment would
        drop the turn for good (the tuning log intel, scan 4877: 0.44 rad, a dead-reckoned
        pose 5 m off 30 m later; 4 of intel's 6 failed fits after a correction over 0.2 rad
        are this)."""
        start = delta.copy()
        start[2] = wrap_angle(float(delta[2] + self.owed))
        assert self._points is not None and self._normals is not None
        info = _prior_information(start, self.motion)
        again, s2 = match_increment(self._points, self._normals, pts, nrm, start, info, self.config)
        if s2 >= self.config.min_inliers and np.all(np.isfinite(again)):
            return again, s2
        return fit, share

    def correct(self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray) -> np.ndarray:
        """The corrected odometry pose of the scan ``ranges`` / ``angles`` taken at the raw
        odometry pose ``odom`` (finite ``[x, y, theta]``, checked by the caller)."""
        raw = np.asarray(odom, dtype=np.float64).reshape(3)
        self.explained = math.nan
        self.matched_from = None
        if self._raw is not None and self._out is not None and np.array_equal(raw, self._raw):
            return self._out.copy()  # stale: repeated as received
        pts, nrm = _surface_points(ranges, angles, self.config)
        if self._raw is None or self._out is None:
            out = raw.copy()
        else:
            delta = compose(invert(self._raw), raw)
            use = delta
            if self._points is not None and len(pts) >= 10 and len(self._points) >= 10:
                step = max(1, len(pts) // self.config.max_points)
                fit, share = match_increment(
                    self._points,
                    self._normals,
                    pts[::step],
                    nrm[::step],
                    delta,
                    _prior_information(delta, self.motion),
                    self.config,
                )
                if share < self.config.min_inliers and self.config.fallback_sigma > 0.0:
                    fit, share = self._fallback(pts[::step], nrm[::step], delta, fit, share)
                if share < self.config.min_inliers and self.owed != 0.0:
                    fit, share = self._deferred(pts[::step], nrm[::step], delta, fit, share)
                self.explained = share
                if share >= self.config.min_inliers and np.all(np.isfinite(fit)):
                    use = fit
                    self.matched_from = self._out.copy()
            self.owed = wrap_angle(float(delta[2] - use[2])) if use is not delta else 0.0
            out = compose(self._out, use)
        self._points, self._normals = pts, nrm
        self._raw = raw.copy()
        self._out = out.copy()
        return out.copy()


@dataclass(frozen=True)
class OdometryStep:
    """One scan's odometry as the localiser uses it: ``reading`` the corrected odometry pose
    (``None``: the scan came without odometry), ``previous`` the last scan's (``None``: none),
    ``delta`` the robot-frame increment between them (``None`` without both), ``step`` its
    length (m), ``matched_from`` the reading the increment was scan-matched from (``None``:
    not matched), ``broken`` whether the scan-to-scan fit failed to match this scan to
    the previous one (a break in what the laser sees: a kidnap, a jump) and ``spread`` the
    increment's translation variance beyond the odometry model's (2x2, m^2, robot frame of
    the previous reading; ``None``: none; a laser odometry's unobserved corridor axis,
    :attr:`service.core.tracking.laser_odometry.LaserStep.spread`)."""

    reading: np.ndarray | None
    previous: np.ndarray | None = None
    delta: np.ndarray | None = None
    step: float = 0.0
    matched_from: np.ndarray | None = None
    broken: bool = False
    spread: np.ndarray | None = None

    def noise(self, c: MotionConfig) -> np.ndarray:
        """Process noise (robot frame) of ``delta`` for dead reckoning: the odometry model
        (:func:`~service.core.tracking.motion.odometry_sigmas`) without its per-scan floors (a
        robot standing still does not drift); an increment a kept scan-to-scan fit measured
        from the previous reading has the turn terms scaled by ``matched_turn_noise``, as in
        the tracker's prior (two scans tell a turn as well as a straight step); ``spread`` (a
        laser odometry's unobserved corridor axis) adds to the position block."""
        assert self.delta is not None
        matched = (
            self.matched_from is not None
            and self.previous is not None
            and bool(np.array_equal(self.matched_from, self.previous))
        )
        s_t, s_r = odometry_sigmas(self.delta, c, matched)
        s_t -= c.sigma_xy_floor
        s_r -= c.sigma_theta_floor
        noise = np.diag([s_t**2, s_t**2, s_r**2])
        if self.spread is not None:
            sp = np.asarray(self.spread, dtype=np.float64).reshape(2, 2)
            noise[:2, :2] += 0.5 * (sp + sp.T)
        return noise


class Odometry:
    """The localiser's one memory of the odometry: each scan's reading corrected by matching
    the scan to the previous one (:class:`ScanOdometry`, or as received when that is off),
    the increment since the last scan and the travel so far. A scan without odometry makes
    the next reading start afresh. Picklable."""

    def __init__(self, motion: MotionConfig) -> None:
        self.motion = motion
        self.check = ScanOdometry(motion.scan_odometry, motion)
        self.last: np.ndarray | None = None
        self.travel = 0.0

    def reset(self, odom: np.ndarray | None = None) -> None:
        """Forget the odometry; ``odom`` (if given) is the reading the next increment starts
        from."""
        o = None if odom is None else np.asarray(odom, dtype=np.float64).copy()
        self.check.reset(o)
        self.last = o

    def step(
        self,
        ranges: np.ndarray,
        angles: np.ndarray,
        odom: np.ndarray | None,
        spread: np.ndarray | None = None,
    ) -> OdometryStep:
        """This scan's :class:`OdometryStep` (``odom`` the raw reading, checked finite;
        ``spread`` its increment's extra translation variance, if any)."""
        if odom is None:
            self.check.reset(None)
            self.last = None
            return OdometryStep(None)
        raw = np.asarray(odom, dtype=np.float64).reshape(3)
        matched = None
        broken = False
        if self.motion.scan_odometry.enabled:
            reading = self.check.correct(ranges, angles, raw)
            matched = self.check.matched_from
            broken = bool(self.check.explained < self.motion.scan_odometry.min_inliers)
        else:
            reading = raw.copy()
        previous = self.last
        delta = None if previous is None else compose(invert(previous), reading)
        step = 0.0 if delta is None else float(np.hypot(delta[0], delta[1]))
        self.travel += step
        self.last = reading.copy()
        sp = None if spread is None or delta is None else np.asarray(spread, dtype=np.float64)
        return OdometryStep(reading, previous, delta, step, matched, broken, sp)
