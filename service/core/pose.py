"""Pose estimation from matched shape features (paper §5: the metric step after matching).

Conventions: a *pose* or a *rigid transform* is ``np.array([tx, ty, phi])`` (metres, radians);
applied to points ``p`` (robot frame or any source frame) it gives ``R(phi) @ p + t``. A robot
pose ``[x, y, theta]`` in the map frame is exactly the transform from the robot frame to the map
frame (REP 103).

The shape matching (:mod:`service.core.shapes.matching`) decides *which* scan polyline corresponds
to *which* map polyline. This module turns those correspondences into a precise pose: points along
every matched scan polyline are paired with the nearest point of the map geometry of *its own*
matched partner only (never of another map polyline), and the rigid transform is solved by
weighted least squares, re-pairing a few times (:func:`pose_from_matches`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import pose as pose_kernels
from service.core.types import wrap_angle
from service.errors import LocalizationError


def rot(phi: float) -> np.ndarray:
    """2x2 rotation matrix for ``phi`` radians (counter-clockwise)."""
    c, s = np.cos(phi), np.sin(phi)
    return np.array([[c, -s], [s, c]])


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply the rigid transform ``pose = [tx, ty, phi]`` to ``(k, 2)`` points (metres)."""
    c, s = np.cos(pose[2]), np.sin(pose[2])
    pts = np.asarray(points, dtype=np.float64)
    out = np.empty_like(pts)
    out[:, 0] = c * pts[:, 0] - s * pts[:, 1] + pose[0]
    out[:, 1] = s * pts[:, 0] + c * pts[:, 1] + pose[1]
    return out


def compose(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Transform ``a ∘ b`` (apply ``b`` first, then ``a``); theta normalised to (-pi, pi]."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array(
        [
            a[0] + c * b[0] - s * b[1],
            a[1] + s * b[0] + c * b[1],
            wrap_angle(a[2] + b[2]),
        ]
    )


def invert(a: np.ndarray) -> np.ndarray:
    """Inverse rigid transform of ``a = [tx, ty, phi]``."""
    c, s = np.cos(a[2]), np.sin(a[2])
    return np.array([-(c * a[0] + s * a[1]), s * a[0] - c * a[1], wrap_angle(-a[2])])


def relative(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The increment ``d`` with ``a ∘ d = b``: pose ``b`` expressed in the frame of ``a``."""
    return compose(invert(a), b)


def mahalanobis2(pose: np.ndarray, mean: np.ndarray, cov: np.ndarray) -> float:
    """Squared Mahalanobis distance of ``pose`` from ``mean`` under ``cov`` (heading wrapped)."""
    e = np.asarray(pose, dtype=np.float64) - mean
    e[2] = wrap_angle(float(e[2]))
    return float(numeric.quadratic(e, numeric.inv(cov)))


def propagate(
    pose: np.ndarray, cov: np.ndarray, delta: np.ndarray, noise: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Dead reckoning: ``pose (+) delta`` and its covariance ``J cov J' + R noise R'`` (``J``
    the Jacobian of the composition in the pose, ``R`` the rotation of the robot frame,
    ``noise`` the increment's, robot frame)."""
    new = compose(pose, delta)
    c, s = math.cos(float(pose[2])), math.sin(float(pose[2]))
    dx = -s * float(delta[0]) - c * float(delta[1])
    dy = c * float(delta[0]) - s * float(delta[1])
    J = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    out = numeric.matmul(numeric.matmul(J, cov), J.T) + numeric.matmul(
        numeric.matmul(R, noise), R.T
    )
    return new, 0.5 * (out + out.T)


def sigma_xy(cov: np.ndarray) -> float:
    """Largest position standard deviation (m) of a pose covariance."""
    return float(math.sqrt(max(0.0, float(numeric.eigh_sym2(cov[:2, :2])[0][-1]))))


def rigid_transform_2d(
    src: np.ndarray, dst: np.ndarray, weights: np.ndarray | None = None
) -> np.ndarray:
    """Least-squares rigid transform (rotation + translation, no reflection, no scale) taking
    ``src`` onto ``dst``: minimises ``sum_i w_i ||R(phi) src_i + t - dst_i||^2`` in closed form
    (2-D Kabsch/Umeyama: the optimal angle is ``atan2`` of the weighted cross/dot sums of the
    centred point sets).

    ``src``/``dst`` are ``(k, 2)`` metres in any frames; ``weights`` ``(k,)`` >= 0 (default 1).
    Returns ``[tx, ty, phi]`` (metres, radians in (-pi, pi]). Raises :class:`LocalizationError`
    on mismatched shapes, fewer than one point with positive weight, or non-finite input.
    """
    a = np.asarray(src, dtype=np.float64)
    b = np.asarray(dst, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 2 or a.shape != b.shape:
        raise LocalizationError(f"rigid_transform_2d: shapes {a.shape} and {b.shape} differ")
    if a.shape[0] == 0:
        raise LocalizationError("rigid_transform_2d: no points")
    w = np.ones(a.shape[0]) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (a.shape[0],) or np.any(w < 0) or not np.all(np.isfinite(w)):
        raise LocalizationError("rigid_transform_2d: weights must be finite, >= 0, one per point")
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        raise LocalizationError("rigid_transform_2d: non-finite point")
    wsum = w.sum()
    if wsum <= 0.0:
        raise LocalizationError("rigid_transform_2d: all weights are zero")
    ca = np.einsum("i,ij->j", w, a) / wsum
    cb = np.einsum("i,ij->j", w, b) / wsum
    a0 = a - ca
    b0 = b - cb
    dot = np.sum(w * (a0[:, 0] * b0[:, 0] + a0[:, 1] * b0[:, 1]))
    cross = np.sum(w * (a0[:, 0] * b0[:, 1] - a0[:, 1] * b0[:, 0]))
    phi = numeric.atan2(cross, dot) if (dot != 0.0 or cross != 0.0) else 0.0
    t = cb - numeric.matvec(rot(phi), ca)
    return np.array([t[0], t[1], wrap_angle(phi)])


def nearest_on_segments(
    points: np.ndarray, segments: np.ndarray, owner_pt: np.ndarray, owner_seg: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For every point, the nearest point on the segments that have the same owner id.

    ``points`` ``(k, 2)``, ``segments`` ``(s, 4)`` ``[x0, y0, x1, y1]`` (same frame, metres),
    ``owner_pt`` ``(k,)`` / ``owner_seg`` ``(s,)`` integer pair ids. Returns ``(foot (k, 2),
    normal (k, 2), dist (k,))``: the foot point, the unit normal of the segment it lies on (for a
    foot clamped to a segment end, the unit vector from foot to point) and the distance; points
    without any segment of their owner get ``dist = inf``.
    """
    a = segments[:, 0:2]
    e = segments[:, 2:4] - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    # (k, s) problem restricted by owner mask.
    dx = points[:, None, 0] - a[None, :, 0]
    dy = points[:, None, 1] - a[None, :, 1]
    u = (dx * e[None, :, 0] + dy * e[None, :, 1]) / ee[None, :]
    uc = np.clip(u, 0.0, 1.0)
    rx = dx - uc * e[None, :, 0]
    ry = dy - uc * e[None, :, 1]
    d2 = rx * rx + ry * ry
    d2 = np.where(owner_pt[:, None] == owner_seg[None, :], d2, np.inf)
    j = np.argmin(d2, axis=1)
    rows = np.arange(points.shape[0])
    dist = np.sqrt(d2[rows, j])
    ucj = uc[rows, j]
    foot = a[j] + ucj[:, None] * e[j]
    en = e[j] / np.sqrt(ee[j])[:, None]
    normal = np.stack([-en[:, 1], en[:, 0]], axis=1)
    clamped = (ucj <= 0.0) | (ucj >= 1.0)
    rvec = points - foot
    rn = np.hypot(rvec[:, 0], rvec[:, 1])
    use_r = clamped & (rn > 1e-12)
    normal[use_r] = rvec[use_r] / rn[use_r, None]
    return foot, normal, dist


@dataclass(frozen=True)
class PoseFit:
    """Result of :func:`pose_from_matches`.

    ``pose`` ``[x, y, theta]`` map frame; ``rms`` inlier point-to-map RMS distance (m);
    ``inliers`` number of scan points used in the last iteration; ``inlier_fraction`` of all
    offered points; ``covariance`` 3x3 (m², rad²) from the Gauss-Newton normal matrix (``None``
    when singular); ``iterations`` performed.
    """

    pose: np.ndarray
    rms: float
    inliers: int
    inlier_fraction: float
    covariance: np.ndarray | None
    iterations: int


@dataclass(frozen=True)
class StackedPairs:
    """Matched pairs for :func:`pose_from_matches` stacked: pair ``k``'s scan points are the
    next ``counts[k]`` rows of ``points`` ``(N, 2)`` and its map segments the rows
    ``seg_start[k] .. seg_start[k] + seg_len[k] - 1`` of ``segments`` ``(S, 4)``; every pair
    has points and segments."""

    points: np.ndarray
    counts: np.ndarray
    segments: np.ndarray
    seg_start: np.ndarray
    seg_len: np.ndarray

    def pairs(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """The pairs one by one."""
        pt = np.cumsum([0, *self.counts.tolist()]).tolist()
        return [
            (self.points[pt[k] : pt[k + 1]], self.segments[s : s + n])
            for k, (s, n) in enumerate(
                zip(self.seg_start.tolist(), self.seg_len.tolist(), strict=True)
            )
        ]


def pose_from_matches(
    pairs: Sequence[tuple[np.ndarray, np.ndarray]] | StackedPairs,
    initial_pose: np.ndarray,
    *,
    iterations: int = 12,
    inlier_distance: float = 0.3,
    robust_scale: float = 0.05,
    damping: float = 1e-3,
    tol: float = 1e-6,
    prior: np.ndarray | None = None,
    prior_weight: float = 0.0,
    covariance: bool = True,
) -> PoseFit:
    """Robot pose from matched polyline pairs (paper §5: the pose that brings the matched scan
    polylines onto their map polylines) by least squares over points of the pairs.

    ``pairs``: one ``(scan_points (k, 2) robot frame, map_segments (s, 4) map frame)`` per
    matched pair of the configuration matching. ``initial_pose`` ``[x, y, theta]`` map frame
    (e.g. the two-step matching's estimate). Each iteration transforms the scan points with the
    current pose, takes for each point the nearest point on the segments of its own pair (points
    farther than ``inlier_distance`` metres are dropped, the rest get Cauchy weights with scale
    ``robust_scale`` metres) and solves the weighted point-to-line least squares for a pose
    increment (Gauss-Newton with a small Levenberg ``damping`` so that degenerate geometry —
    a single straight wall — keeps the estimate along the free direction). Stops when the
    increment is below ``tol`` (m and rad) or after ``iterations``.

    ``prior`` ``[x, y, theta]`` with ``prior_weight`` > 0 adds a weak pull of the position
    towards the prior's (as if ``prior_weight`` fully weighted points pinned it): it only
    matters where the matched geometry leaves a direction unobservable (a corridor).

    Raises :class:`LocalizationError` when no pair has points and segments.

    ``pairs`` may also be a :class:`StackedPairs` (what the matcher builds without copying
    each pair). ``covariance=False`` leaves :attr:`PoseFit.covariance` ``None`` (a caller
    that only wants the pose saves the 3x3 inverse).

    The loop runs in a compiled kernel (:func:`service.core.kernels.pose.pose_iterations`) when
    numba is available, else in :func:`_pose_from_matches_numpy` (the reference).
    """
    if not kernels.HAVE_NUMBA:
        fit = _pose_from_matches_numpy(
            pairs.pairs() if isinstance(pairs, StackedPairs) else pairs,
            initial_pose,
            iterations=iterations,
            inlier_distance=inlier_distance,
            robust_scale=robust_scale,
            damping=damping,
            tol=tol,
            prior=prior,
            prior_weight=prior_weight,
        )
        return fit if covariance else dataclasses.replace(fit, covariance=None)
    if isinstance(pairs, StackedPairs):
        if len(pairs.counts) == 0:
            raise LocalizationError("pose_from_matches: no matched pair with points and segments")
        own = np.repeat(np.arange(len(pairs.counts)), pairs.counts)
        pts_all = np.ascontiguousarray(pairs.points, dtype=np.float64)
        segs_all = np.ascontiguousarray(pairs.segments, dtype=np.float64)
        seg_start = np.ascontiguousarray(pairs.seg_start, dtype=np.intp)
        seg_len = np.ascontiguousarray(pairs.seg_len, dtype=np.intp)
    else:
        pts_list, seg_list = [], []
        for pts, segs in pairs:
            pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
            segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
            if pts.shape[0] == 0 or segs.shape[0] == 0:
                continue
            pts_list.append(pts)
            seg_list.append(segs)
        if not pts_list:
            raise LocalizationError("pose_from_matches: no matched pair with points and segments")
        K = len(pts_list)
        own = np.repeat(np.arange(K), [len(x) for x in pts_list])
        seg_len = np.array([len(x) for x in seg_list], dtype=np.intp)
        seg_start = np.concatenate(([0], np.cumsum(seg_len)[:-1])).astype(np.intp)
        pts_all = np.ascontiguousarray(np.vstack(pts_list))
        segs_all = np.ascontiguousarray(np.vstack(seg_list))
    use_prior = prior is not None and prior_weight > 0.0
    pose, H, rms, n_in, it, have_h = pose_kernels.pose_iterations(
        pts_all,
        own,
        segs_all,
        seg_start,
        seg_len,
        np.asarray(initial_pose, dtype=np.float64).copy(),
        int(iterations),
        float(inlier_distance),
        float(robust_scale),
        float(damping),
        float(tol),
        np.asarray(prior if use_prior else np.zeros(3), dtype=np.float64),
        float(prior_weight) if use_prior else 0.0,
    )
    total = len(own)
    cov = None
    if covariance and have_h and n_in > 3:
        sigma2 = max(float(rms), 1e-3) ** 2
        try:
            cov = sigma2 * numeric.inv(H)
        except np.linalg.LinAlgError:
            cov = None
    return PoseFit(
        pose=pose,
        rms=float(rms),
        inliers=int(n_in),
        inlier_fraction=int(n_in) / total,
        covariance=cov,
        iterations=int(it),
    )


def _pose_from_matches_numpy(
    pairs: Sequence[tuple[np.ndarray, np.ndarray]],
    initial_pose: np.ndarray,
    *,
    iterations: int = 12,
    inlier_distance: float = 0.3,
    robust_scale: float = 0.05,
    damping: float = 1e-3,
    tol: float = 1e-6,
    prior: np.ndarray | None = None,
    prior_weight: float = 0.0,
) -> PoseFit:
    """Numpy reference of :func:`pose_from_matches` (same arguments and result)."""
    pts_list, seg_list, own_p, own_s = [], [], [], []
    for k, (pts, segs) in enumerate(pairs):
        pts = np.asarray(pts, dtype=np.float64).reshape(-1, 2)
        segs = np.asarray(segs, dtype=np.float64).reshape(-1, 4)
        if pts.shape[0] == 0 or segs.shape[0] == 0:
            continue
        pts_list.append(pts)
        seg_list.append(segs)
        own_p.append(np.full(pts.shape[0], k))
        own_s.append(np.full(segs.shape[0], k))
    if not pts_list:
        raise LocalizationError("pose_from_matches: no matched pair with points and segments")
    P = np.vstack(pts_list)
    S = np.vstack(seg_list)
    op = np.concatenate(own_p)
    os_ = np.concatenate(own_s)
    pose = np.asarray(initial_pose, dtype=np.float64).copy()
    total = P.shape[0]
    H = None
    rms = float("inf")
    n_in = 0
    it = 0
    for it in range(1, iterations + 1):  # noqa: B007
        Q = transform_points(pose, P)
        _foot, normal, dist = nearest_on_segments(Q, S, op, os_)
        inl = dist <= inlier_distance
        n_in = int(inl.sum())
        if n_in < 3:
            break
        q = Q[inl]
        n = normal[inl]
        r = np.einsum("ij,ij->i", q - _foot[inl], n)  # signed point-to-line residual
        w = 1.0 / (1.0 + (r / robust_scale) ** 2)
        lever = q - pose[:2]
        J = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * lever[:, 0] - n[:, 0] * lever[:, 1]])
        H = numeric.matmul((J * w[:, None]).T, J)
        g = numeric.matvec((J * w[:, None]).T, r)
        if prior is not None and prior_weight > 0.0:
            H[0, 0] += prior_weight
            H[1, 1] += prior_weight
            g[0] += prior_weight * (pose[0] - prior[0])
            g[1] += prior_weight * (pose[1] - prior[1])
        scale = max(float(np.trace(H)) / 3.0, 1e-12)
        delta = -numeric.solve(H + damping * scale * np.eye(3), g)
        # Increment of the pose parameters themselves (q = R(theta) p + t, derivatives at fixed t).
        pose = np.array([pose[0] + delta[0], pose[1] + delta[1], wrap_angle(pose[2] + delta[2])])
        rms = float(np.sqrt(np.sum(w * r * r) / max(np.sum(w), 1e-12)))
        if np.hypot(delta[0], delta[1]) < tol and abs(delta[2]) < tol:
            break
    cov = None
    if H is not None and n_in > 3:
        sigma2 = max(rms, 1e-3) ** 2
        try:
            cov = sigma2 * numeric.inv(H)
        except np.linalg.LinAlgError:
            cov = None
    return PoseFit(
        pose=pose,
        rms=rms,
        inliers=n_in,
        inlier_fraction=n_in / total,
        covariance=cov,
        iterations=it,
    )
