"""The precise fit: a robust point-to-line alignment of a whole scan to the map.

Shape matching (§5) finds *which* scan structures belong to *which* map structures even far
from the prior and without local minima; it is not what makes a pose precise to millimetres on
a real map. :func:`refine_pose` does that last step: every scan point (optionally weighted,
e.g. by whether shape matching matched its polyline) is associated with the nearest map
segment whose orientation agrees with the point's local surface normal
(:meth:`service.core.sensor.mapmodel.MapModel.nearest`), and the pose minimises

    sum_i w_i rho(n_i . (R p_i + t - f_i))  +  (x - x_prior)^T Lambda (x - x_prior)

by Gauss-Newton with re-association every iteration: ``rho`` is Cauchy with scale
``robust_scale``, pairs farther than a trimming distance (shrinking from ``trim_initial`` to
``trim_final``) are ignored, and ``Lambda`` is the motion model's information
(:mod:`service.core.tracking.motion`), which only matters where the scan leaves a direction
unobservable (a corridor). Units: metres, radians; ``points`` robot frame, poses map frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.core import kernels, numeric
from service.core.kernels import map as map_kernels
from service.core.pose import PoseFit, transform_points
from service.core.sensor.mapmodel import MapModel, nearest_numpy
from service.core.types import wrap_angle
from service.errors import LocalizationError


class RefineParams(BaseModel):
    """Parameters of :func:`refine_pose` (metres, radians)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    iterations: int = Field(20, ge=1, description="Gauss-Newton iterations at most.")
    trim_initial: float = Field(0.5, gt=0, description="Association distance, first step (m).")
    trim_final: float = Field(0.2, gt=0, description="Association distance, last steps (m).")
    trim_decay: float = Field(0.7, gt=0, le=1, description="Trim factor per iteration.")
    robust_scale: float = Field(0.03, gt=0, description="Cauchy scale of the residuals (m).")
    normal_gate: float = Field(
        0.8, gt=0, le=np.pi / 2, description="Largest angle between scan and map normals (rad)."
    )
    damping: float = Field(1e-4, ge=0, description="Levenberg damping relative to the trace.")
    tol: float = Field(1e-5, gt=0, description="Stop when the increment is below (m, rad).")
    inlier_tolerance: float = Field(
        0.1, gt=0, description="A point within this of the map counts as explained (m)."
    )
    point_sigma: float = Field(
        0.03, gt=0, description="Residual sigma that scales the points against the prior (m)."
    )
    likelihood_sigma: float = Field(
        0.05, gt=0, description="Sigma of the per-point likelihood used to compare fits (m)."
    )
    effective_points: float = Field(
        0.0,
        ge=0,
        description="Neighbouring returns are correlated (one wall, one piece of furniture): "
        "the points of a scan carry about this many independent residuals' worth of "
        "information against the prior, whatever their number (0 = every point counts "
        "fully). Schematic: 50 with an odometry prior (the shape tracker keeps the velocity "
        "prior at 0) -- where the plan explains little of the scan, the few walls it does "
        "explain must not outweigh the odometry step by hundreds of points.",
    )
    likelihood_floor: float = Field(
        0.05,
        gt=0,
        description="Per-point likelihood of an unexplained return (clutter, "
        "people, missing map parts), relative to a perfect hit.",
    )


@dataclass(frozen=True)
class Refined:
    """A :func:`refine_pose` result: the fit (a :class:`~service.core.pose.PoseFit`) and the
    signed point-to-line residuals at its pose (``inf``: no map segment within the final
    trim), with the statistics methods compare fits by."""

    fit: PoseFit
    residuals: np.ndarray
    loglik: float

    @property
    def pose(self) -> np.ndarray:
        return self.fit.pose

    @property
    def inlier_fraction(self) -> float:
        return self.fit.inlier_fraction

    def weighted_loglik(self, weights: np.ndarray, params: RefineParams) -> float:
        """Mean per-point log-likelihood with per-point ``weights`` (see :func:`refine_pose`)."""
        return float(np.average(_point_loglik(self.residuals, params), weights=weights))


def _point_loglik(residuals: np.ndarray, params: RefineParams) -> np.ndarray:
    """``log(floor + exp(-r^2 / 2 sigma^2))`` per residual (inf: an unexplained return)."""
    r = np.minimum(np.abs(residuals), 1e3) / params.likelihood_sigma
    return numeric.log(params.likelihood_floor + numeric.exp(-0.5 * r * r))


def scan_normals(
    points: np.ndarray,
    max_gap: float = 0.25,
    gap_factor: float = 0.05,
    *,
    starts: np.ndarray | None = None,
) -> np.ndarray:
    """Unit surface normals ``(n, 2)`` of beam-ordered scan points (robot frame).

    The tangent at a point is the chord between its two neighbours (or the one neighbour it
    has) when they lie within ``max_gap + gap_factor * range`` metres; a point with no close
    neighbour gets a NaN normal (no orientation constraint). ``starts``: rows where a new
    polyline begins, for several polylines stacked (neighbours are taken within a polyline
    only; the same normals as for each polyline alone).
    """
    p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    n = len(p)
    if kernels.HAVE_NUMBA and n >= 2:
        cut = np.zeros(n, dtype=np.bool_)
        if starts is not None:
            c = np.asarray(starts, dtype=np.intp)
            cut[c[(c > 0) & (c < n)]] = True
        return map_kernels.scan_normals(np.ascontiguousarray(p), max_gap, gap_factor, cut)
    out = np.full((n, 2), np.nan)
    if n < 2:
        return out
    rng = np.hypot(p[:, 0], p[:, 1])
    lim = max_gap + gap_factor * rng
    gap = np.hypot(*np.diff(p, axis=0).T)
    prev_ok = np.zeros(n, dtype=bool)
    next_ok = np.zeros(n, dtype=bool)
    prev_ok[1:] = gap <= lim[1:]
    next_ok[:-1] = gap <= lim[:-1]
    if starts is not None:
        cut = np.asarray(starts, dtype=np.intp)
        cut = cut[(cut > 0) & (cut < n)]
        prev_ok[cut] = False
        next_ok[cut - 1] = False
    a = np.where(prev_ok[:, None], np.vstack([p[:1], p[:-1]]), p)
    b = np.where(next_ok[:, None], np.vstack([p[1:], p[-1:]]), p)
    t = b - a
    tn = np.hypot(t[:, 0], t[:, 1])
    ok = (prev_ok | next_ok) & (tn > 1e-9)
    out[ok, 0] = -t[ok, 1] / tn[ok]
    out[ok, 1] = t[ok, 0] / tn[ok]
    return out


def refine_pose(
    model: MapModel,
    points: np.ndarray,
    initial: np.ndarray,
    params: RefineParams,
    *,
    normals: np.ndarray | None = None,
    weights: np.ndarray | None = None,
    prior: np.ndarray | None = None,
    prior_information: np.ndarray | None = None,
) -> Refined:
    """Fit ``points`` ``(n, 2)`` (robot frame) to ``model`` from ``initial`` ``[x, y, theta]``.

    ``normals`` ``(n, 2)`` robot-frame unit normals (NaN: unconstrained; default: from
    :func:`scan_normals`); ``weights`` ``(n,)`` >= 0 (default 1); ``prior`` and its 3x3
    ``prior_information`` (map frame) add the motion model's term (default: none). Returns a
    :class:`Refined`: its ``fit.inliers`` / ``inlier_fraction`` count points within
    ``params.inlier_tolerance`` of the map at the final pose (fraction of all points),
    ``fit.rms`` is their RMS residual, ``fit.covariance`` ``point_sigma^2 H^-1`` from the
    points' normal matrix (``None`` when singular), and ``loglik`` the mean per-point
    log-likelihood ``log(floor + exp(-r^2 / 2 sigma^2))`` (robust: an unexplained return
    costs ``log(floor)``, whatever its distance).
    """
    pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 2))
    if len(pts) == 0:
        raise LocalizationError("refine_pose: no scan points")
    init = np.asarray(initial, dtype=np.float64).reshape(3).copy()
    if not np.all(np.isfinite(init)):
        raise LocalizationError("refine_pose: initial pose must be finite")
    nrm = scan_normals(pts) if normals is None else np.asarray(normals, dtype=np.float64)
    nrm = np.ascontiguousarray(nrm.reshape(-1, 2))
    w = np.ones(len(pts)) if weights is None else np.asarray(weights, dtype=np.float64)
    w = np.ascontiguousarray(w.reshape(-1))
    if nrm.shape != pts.shape or w.shape != (len(pts),):
        raise LocalizationError("refine_pose: normals / weights do not match the points")
    scale2 = params.point_sigma**2
    if prior is None or prior_information is None:
        pr = init.copy()
        info = np.zeros((3, 3))
    else:
        pr = np.asarray(prior, dtype=np.float64).reshape(3).copy()
        # the points' normal matrix is in units of 1/m^2 per unit weight; scale the prior
        # information so that both speak residual variances
        info = np.asarray(prior_information, dtype=np.float64).reshape(3, 3) * scale2
        total = float(w.sum())
        if params.effective_points > 0 and total > params.effective_points:
            info = info * (total / params.effective_points)
    trim0 = min(max(params.trim_initial, params.trim_final), model.reach)
    trim1 = min(params.trim_final, model.reach)
    cg = float(np.cos(params.normal_gate)) if params.normal_gate < np.pi / 2 else -1.0
    args = (
        int(params.iterations),
        float(trim0),
        float(trim1),
        float(params.trim_decay),
        float(params.robust_scale),
        cg,
        float(params.damping),
        float(params.tol),
    )
    if kernels.HAVE_NUMBA:
        pose, H, res, it = map_kernels.refine_iterations(
            pts, nrm, w, *model.grid_args(), init, pr, np.ascontiguousarray(info), *args
        )
    else:
        pose, H, res, it = _refine_numpy(model, pts, nrm, w, init, pr, info, *args)
    ar = np.abs(res)
    inl = ar <= params.inlier_tolerance
    n_in = int(inl.sum())
    rms = float(np.sqrt(np.mean(res[inl] ** 2))) if n_in else float("inf")
    loglik = float(np.mean(_point_loglik(res, params)))
    cov = None
    if n_in > 3:
        try:
            cov = scale2 * numeric.inv(H)
            if not np.all(np.isfinite(cov)):
                cov = None
        except np.linalg.LinAlgError:
            cov = None
    pose = np.array([pose[0], pose[1], wrap_angle(float(pose[2]))])
    fit = PoseFit(
        pose=pose,
        rms=rms,
        inliers=n_in,
        inlier_fraction=n_in / len(pts),
        covariance=cov,
        iterations=int(it),
    )
    return Refined(fit=fit, residuals=res, loglik=loglik)


def _refine_numpy(
    model: MapModel,
    pts: np.ndarray,
    nrm: np.ndarray,
    w: np.ndarray,
    init: np.ndarray,
    prior: np.ndarray,
    info: np.ndarray,
    iterations: int,
    trim_initial: float,
    trim_final: float,
    trim_decay: float,
    scale: float,
    cos_gate: float,
    damping: float,
    tol: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Reference of :func:`service.core.kernels.map.refine_iterations`."""

    def terms(pose: np.ndarray, trim: float) -> tuple:
        q = transform_points(pose, pts)
        c, s = np.cos(pose[2]), np.sin(pose[2])
        qn = np.column_stack([c * nrm[:, 0] - s * nrm[:, 1], s * nrm[:, 0] + c * nrm[:, 1]])
        seg, _d, foot, m = nearest_numpy(model, q, qn, trim, cos_gate)
        ok = seg >= 0
        r = np.einsum("ij,ij->i", m[ok], q[ok] - foot[ok])
        jt = m[ok, 0] * (-(q[ok, 1] - pose[1])) + m[ok, 1] * (q[ok, 0] - pose[0])
        J = np.column_stack([m[ok, 0], m[ok, 1], jt])
        ww = w[ok] / (1.0 + (r / scale) ** 2)
        return ok, r, J, ww

    pose = init.copy()
    trim = trim_initial
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007 (the count is returned)
        _ok, r, J, ww = terms(pose, trim)
        H = numeric.matmul(J.T, J * ww[:, None])
        g = numeric.matvec(J.T, ww * r)
        e = np.array([pose[0] - prior[0], pose[1] - prior[1], wrap_angle(pose[2] - prior[2])])
        A = H + info + (damping * np.trace(H) / 3.0 + 1e-9) * np.eye(3)
        dx = numeric.solve(A, -(g + numeric.matvec(info, e)))
        pose = np.array([pose[0] + dx[0], pose[1] + dx[1], wrap_angle(pose[2] + dx[2])])
        trim = max(trim_final, trim * trim_decay)
        if np.all(np.abs(dx) < tol) and trim <= trim_final:
            break
    ok, r, J, ww = terms(pose, trim)
    H = numeric.matmul(J.T, J * ww[:, None])
    res = np.full(len(pts), np.inf)
    res[ok] = r
    return pose, H, res, it
