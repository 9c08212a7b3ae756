"""Many candidate poses fitted at once, each to its own paired scan points and map segments:
the short, damped least-squares fits that rank and polish the poses a matching or a search
induces (:mod:`service.core.shapes.matching`, :mod:`service.core.reloc.global_search`), as opposed
to the one precise fit of a matched configuration (:func:`service.core.pose.pose_from_matches`).
Each function runs a compiled kernel (:mod:`service.core.kernels.pose`) when numba is
available, else the same iterations in numpy.

Conventions as in :mod:`service.core.pose`: poses ``[x, y, theta]`` map frame (metres,
radians), points robot frame, segments ``(x0, y0, x1, y1)`` map frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import pose as pose_kernels
from service.core.types import wrap_angle


def fit_pairs(
    points: Sequence[np.ndarray],
    segments: Sequence[np.ndarray],
    initial_pose: np.ndarray,
    *,
    iterations: int = 3,
    robust_scale: float = 0.1,
    damping: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Independent point-to-line fit of each pair, all pairs at once (vectorised).

    Pair ``k`` is ``(points[k] (n_k, 2) robot frame, segments[k] (s_k, 4) map frame)``; each
    pair's pose is refined from ``initial_pose`` ``[x, y, theta]`` (or one per pair, ``(K, 3)``)
    by ``iterations``
    Gauss-Newton steps of the point-to-line distance, with Cauchy weights (scale
    ``robust_scale`` metres) and Levenberg ``damping`` (relative to the normal matrix trace) so
    that a direction the pair cannot observe (along a straight wall) stays at the initial value.
    Used for the alignment a corresponding pair induces (eq. 4/5's ``A(P, Q)``).

    Returns ``(poses (K, 3), rms (K,))``: the pose each pair induces and its weighted RMS
    point-to-line residual (m).
    """
    K = len(points)
    if K == 0:
        return np.zeros((0, 3)), np.zeros(0)
    counts = np.array([len(p) for p in points])
    P = np.vstack([np.asarray(p, dtype=np.float64).reshape(-1, 2) for p in points])
    own = np.repeat(np.arange(K), counts)
    if kernels.HAVE_NUMBA:
        segs = [np.asarray(s, dtype=np.float64).reshape(-1, 4) for s in segments]
        seg_len = np.array([len(s) for s in segs], dtype=np.intp)
        return fit_pairs_blocks(
            P,
            own,
            np.vstack(segs),
            np.concatenate(([0], np.cumsum(seg_len)[:-1])).astype(np.intp),
            seg_len,
            initial_pose,
            iterations=iterations,
            robust_scale=robust_scale,
            damping=damping,
        )
    smax = max(len(s) for s in segments)
    Sg = np.zeros((K, smax, 4))
    valid = np.zeros((K, smax), dtype=bool)
    for k, s in enumerate(segments):
        s = np.asarray(s, dtype=np.float64).reshape(-1, 4)
        Sg[k, : len(s)] = s
        valid[k, : len(s)] = True
    return fit_pairs_stacked(
        P,
        own,
        Sg,
        valid,
        initial_pose,
        iterations=iterations,
        robust_scale=robust_scale,
        damping=damping,
    )


def fit_pairs_stacked(
    P: np.ndarray,
    own: np.ndarray,
    Sg: np.ndarray,
    valid: np.ndarray,
    initial_pose: np.ndarray,
    *,
    iterations: int = 3,
    robust_scale: float = 0.1,
    damping: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_pairs` on pre-stacked arrays: ``P`` ``(N, 2)`` all pairs' points (robot
    frame), ``own`` ``(N,)`` their pair index in ``0..K-1``, ``Sg`` ``(K, smax, 4)`` each pair's
    map segments padded to a common length and ``valid`` ``(K, smax)`` which of them are real.
    Runs :func:`fit_pairs_blocks` when numba is available, else the numpy reference.
    """
    if kernels.HAVE_NUMBA:
        seg_len = valid.sum(axis=1).astype(np.intp)
        return fit_pairs_blocks(
            P,
            own,
            Sg[valid],
            np.concatenate(([0], np.cumsum(seg_len)[:-1])).astype(np.intp),
            seg_len,
            initial_pose,
            iterations=iterations,
            robust_scale=robust_scale,
            damping=damping,
        )
    return _fit_pairs_stacked_numpy(
        P,
        own,
        Sg,
        valid,
        initial_pose,
        iterations=iterations,
        robust_scale=robust_scale,
        damping=damping,
    )


def fit_pairs_ranges(
    P: np.ndarray,
    pt_beg: np.ndarray,
    pt_end: np.ndarray,
    segs: np.ndarray,
    seg_start: np.ndarray,
    seg_len: np.ndarray,
    initial_pose: np.ndarray,
    *,
    iterations: int = 3,
    robust_scale: float = 0.1,
    damping: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_pairs_blocks` where pair ``k``'s points are the run of rows
    ``P[pt_beg[k] : pt_end[k]]`` (runs may overlap: nothing is copied)."""
    pt_beg = np.asarray(pt_beg, dtype=np.intp)
    pt_end = np.asarray(pt_end, dtype=np.intp)
    if not kernels.HAVE_NUMBA or len(pt_beg) == 0:
        lens = pt_end - pt_beg
        own = np.repeat(np.arange(len(pt_beg)), lens)
        rows = np.arange(int(lens.sum())) - np.repeat(np.cumsum(lens) - lens, lens)
        return fit_pairs_blocks(
            P[np.repeat(pt_beg, lens) + rows],
            own,
            segs,
            seg_start,
            seg_len,
            initial_pose,
            iterations=iterations,
            robust_scale=robust_scale,
            damping=damping,
        )
    return _fit_kernel(
        P,
        np.arange(len(P), dtype=np.intp),
        pt_beg,
        pt_end,
        segs,
        seg_start,
        seg_len,
        initial_pose,
        iterations,
        robust_scale,
        damping,
    )


def _fit_kernel(
    P: np.ndarray,
    pt_order: np.ndarray,
    pt_beg: np.ndarray,
    pt_end: np.ndarray,
    segs: np.ndarray,
    seg_start: np.ndarray,
    seg_len: np.ndarray,
    initial_pose: np.ndarray,
    iterations: int,
    robust_scale: float,
    damping: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Run :func:`service.core.kernels.pose.fit_blocks`: pair ``k`` owns the points
    ``P[pt_order[pt_beg[k]:pt_end[k]]]`` and the segments ``segs[seg_start[k]:][:seg_len[k]]``;
    ``initial_pose`` is one pose for all pairs or one per pair."""
    init = np.asarray(initial_pose, dtype=np.float64)
    poses0 = init.copy() if init.ndim == 2 else np.tile(init, (len(seg_len), 1))
    poses, rms = pose_kernels.fit_blocks(
        np.ascontiguousarray(P, dtype=np.float64),
        pt_order,
        pt_beg,
        pt_end,
        np.ascontiguousarray(segs, dtype=np.float64),
        np.ascontiguousarray(seg_start, dtype=np.intp),
        np.ascontiguousarray(seg_len, dtype=np.intp),
        np.ascontiguousarray(poses0),
        int(iterations),
        float(robust_scale),
        float(damping),
    )
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses, rms


def fit_pairs_blocks(
    P: np.ndarray,
    own: np.ndarray,
    segs: np.ndarray,
    seg_start: np.ndarray,
    seg_len: np.ndarray,
    initial_pose: np.ndarray,
    *,
    iterations: int = 3,
    robust_scale: float = 0.1,
    damping: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`fit_pairs` with each pair's segments a run of rows of one array: pair ``k``'s
    map segments are ``segs[seg_start[k] : seg_start[k] + seg_len[k]]`` (``segs`` ``(S, 4)``),
    its points the rows of ``P`` ``(N, 2)`` with ``own == k``. Compiled kernel
    (:func:`service.core.kernels.pose.fit_blocks`) when numba is available, else the numpy
    reference on padded arrays."""
    init = np.asarray(initial_pose, dtype=np.float64)
    K = len(seg_len)
    poses0 = init.copy() if init.ndim == 2 else np.tile(init, (K, 1))
    if K == 0:
        return np.zeros((0, 3)), np.zeros(0)
    if not kernels.HAVE_NUMBA:
        smax = int(seg_len.max())
        col = np.arange(smax)
        valid = col[None, :] < seg_len[:, None]
        idx = np.minimum(seg_start[:, None] + col[None, :], max(len(segs) - 1, 0))
        return _fit_pairs_stacked_numpy(
            P,
            own,
            segs[idx],
            valid,
            poses0,
            iterations=iterations,
            robust_scale=robust_scale,
            damping=damping,
        )
    own = np.asarray(own, dtype=np.intp)
    if len(own) > 1 and np.any(own[1:] < own[:-1]):
        pt_order = np.argsort(own, kind="stable").astype(np.intp)
    else:
        pt_order = np.arange(len(own), dtype=np.intp)
    pt_start = np.searchsorted(own[pt_order], np.arange(K + 1)).astype(np.intp)
    return _fit_kernel(
        P,
        pt_order,
        pt_start[:-1],
        pt_start[1:],
        segs,
        seg_start,
        seg_len,
        poses0,
        iterations,
        robust_scale,
        damping,
    )


def _fit_pairs_stacked_numpy(
    P: np.ndarray,
    own: np.ndarray,
    Sg: np.ndarray,
    valid: np.ndarray,
    initial_pose: np.ndarray,
    *,
    iterations: int = 3,
    robust_scale: float = 0.1,
    damping: float = 0.05,
) -> tuple[np.ndarray, np.ndarray]:
    """Numpy reference of :func:`fit_pairs_stacked` (padded arrays, same result)."""
    K = Sg.shape[0]
    a = Sg[:, :, 0:2]
    e = Sg[:, :, 2:4] - a
    ee = np.maximum(np.einsum("ksi,ksi->ks", e, e), 1e-18)
    init = np.asarray(initial_pose, dtype=np.float64)
    poses = init.copy() if init.ndim == 2 else np.tile(init, (K, 1))
    rms = np.zeros(K)
    eye = np.eye(3)
    # Per-point views of its pair's segments (the same in every iteration).
    ao = a[own]  # (N, smax, 2)
    eo = e[own]
    eeo = ee[own]
    vo = valid[own]
    rows = np.arange(P.shape[0])
    for _ in range(iterations):
        po = poses[own]
        c = np.cos(po[:, 2])
        s_ = np.sin(po[:, 2])
        qx = c * P[:, 0] - s_ * P[:, 1] + po[:, 0]
        qy = s_ * P[:, 0] + c * P[:, 1] + po[:, 1]
        dx = qx[:, None] - ao[:, :, 0]
        dy = qy[:, None] - ao[:, :, 1]
        t = np.clip((dx * eo[:, :, 0] + dy * eo[:, :, 1]) / eeo, 0.0, 1.0)
        rx = dx - t * eo[:, :, 0]
        ry = dy - t * eo[:, :, 1]
        d2 = np.where(vo, rx * rx + ry * ry, np.inf)
        j = np.argmin(d2, axis=1)
        tj = t[rows, j]
        ej = eo[rows, j]
        en = ej / np.sqrt(eeo[rows, j])[:, None]
        nx, ny = -en[:, 1], en[:, 0]
        rvx, rvy = rx[rows, j], ry[rows, j]
        clamped = (tj <= 0.0) | (tj >= 1.0)
        rn = np.hypot(rvx, rvy)
        use = clamped & (rn > 1e-12)
        nx = np.where(use, rvx / np.where(use, rn, 1.0), nx)
        ny = np.where(use, rvy / np.where(use, rn, 1.0), ny)
        r = rvx * nx + rvy * ny
        w = 1.0 / (1.0 + (r / robust_scale) ** 2)
        lx = qx - po[:, 0]
        ly = qy - po[:, 1]
        J = np.column_stack([nx, ny, ny * lx - nx * ly])
        Jw = J * w[:, None]
        H = np.empty((K, 3, 3))
        g = np.empty((K, 3))
        for k1 in range(3):
            g[:, k1] = np.bincount(own, weights=Jw[:, k1] * r, minlength=K)
            for k2 in range(k1, 3):
                H[:, k1, k2] = np.bincount(own, weights=Jw[:, k1] * J[:, k2], minlength=K)
                H[:, k2, k1] = H[:, k1, k2]
        tr = np.maximum(np.trace(H, axis1=1, axis2=2) / 3.0, 1e-12)
        delta = -numeric.solve(H + damping * tr[:, None, None] * eye, g)
        poses = poses + delta
        wsum = np.bincount(own, weights=w, minlength=K)
        rms = np.sqrt(np.bincount(own, weights=w * r * r, minlength=K) / np.maximum(wsum, 1e-12))
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses, rms
