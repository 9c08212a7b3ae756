"""Compiled inner loops of the pose fits (implementation details, numba; the conventions of
:mod:`service.core.kernels`: the arithmetic follows the numpy references expression by
expression, no ``fastmath``).

- :func:`fit_blocks`: the ΔA fits of many (polyline pair, block) candidates at once, for
  :func:`service.core.sensor.pose_batch.fit_pairs_stacked`;
- :func:`pose_iterations`: the robust Gauss-Newton loop of
  :func:`service.core.pose.pose_from_matches`.

Split out of :mod:`service.core.kernels` (which keeps the shared helpers ``wrap`` and
``solve3``) when that file passed 1 100 lines.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.kernels import njit, solve3, solve3_into, wrap


# error_model="numpy": no zero-division checks, so the point loops vectorise; no divisor here
# can be zero (see >= 1e-18, robust_scale > 0, 1 + z^2 >= 1, rn > 1e-12).
@njit(cache=True, nogil=True, error_model="numpy")
def fit_blocks(
    P: np.ndarray,
    pt_order: np.ndarray,
    pt_beg: np.ndarray,
    pt_end: np.ndarray,
    segs: np.ndarray,
    seg_start: np.ndarray,
    seg_len: np.ndarray,
    init: np.ndarray,
    iterations: int,
    robust_scale: float,
    damping: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Kernel of :func:`service.core.sensor.pose_batch.fit_pairs_stacked`.

    ``P`` ``(N, 2)`` points; pair ``k``'s points are ``P[pt_order[pt_beg[k] : pt_end[k]]]``
    (in increasing row order, as numpy's ``bincount`` sums them) and its
    segments rows ``seg_start[k] .. seg_start[k] + seg_len[k] - 1`` of ``segs`` ``(S, 4)``;
    ``init`` ``(K, 3)``. Returns ``(poses (K, 3) unwrapped, rms (K,))``.

    Per pair and iteration the points are moved, then every segment is tried for all points
    (segments in order, a point keeps the first nearest: the same choice as trying a point's
    segments in order), then the residuals and weights are formed and summed in point order:
    each number is computed by the same operations as the reference, in loops over points
    that the compiler can vectorise.
    """
    K = init.shape[0]
    poses = init.copy()
    rms = np.zeros(K)
    S = segs.shape[0]
    sax = np.empty(S)
    say = np.empty(S)
    sex = np.empty(S)
    sey = np.empty(S)
    see = np.empty(S)
    snx = np.empty(S)
    sny = np.empty(S)
    for s in range(S):
        sax[s] = segs[s, 0]
        say[s] = segs[s, 1]
        ex = segs[s, 2] - segs[s, 0]
        ey = segs[s, 3] - segs[s, 1]
        sex[s] = ex
        sey[s] = ey
        v = ex * ex + ey * ey
        see[s] = v if v > 1e-18 else 1e-18
        sq = math.sqrt(see[s])
        snx[s] = -(ey / sq)
        sny[s] = ex / sq
    A = np.empty((3, 3))
    b = np.empty(3)
    most = 0
    for k in range(K):
        most = max(most, pt_end[k] - pt_beg[k])
    # per point of the current pair: robot-frame and moved point, nearest segment (index,
    # squared distance, parameter, residual vector), normal, residual, weight, Jacobian
    px = np.empty(most)
    py = np.empty(most)
    qx = np.empty(most)
    qy = np.empty(most)
    best = np.empty(most)
    bj = np.empty(most, dtype=np.intp)
    bt = np.empty(most)
    brx = np.empty(most)
    bry = np.empty(most)
    nx = np.zeros(most)
    ny = np.zeros(most)
    rr = np.empty(most)
    ww = np.empty(most)
    jj = np.empty(most)
    for k in range(K):
        s0 = seg_start[k]
        s1 = s0 + seg_len[k]
        t0 = pt_beg[k]
        npt = pt_end[k] - t0
        for t in range(npt):
            i = pt_order[t0 + t]
            px[t] = P[i, 0]
            py[t] = P[i, 1]
        for _ in range(iterations):
            px0 = poses[k, 0]
            py0 = poses[k, 1]
            c = math.cos(poses[k, 2])
            sn = math.sin(poses[k, 2])
            for t in range(npt):
                x = px[t]
                y = py[t]
                qx[t] = c * x - sn * y + px0
                qy[t] = sn * x + c * y + py0
                best[t] = np.inf
                bj[t] = -1
                bt[t] = 0.0
                brx[t] = 0.0
                bry[t] = 0.0
            for s in range(s0, s1):
                ex = sex[s]
                ey = sey[s]
                ax = sax[s]
                ay = say[s]
                ee = see[s]
                for t in range(npt):
                    dx = qx[t] - ax
                    dy = qy[t] - ay
                    u = (dx * ex + dy * ey) / ee
                    u = 0.0 if u < 0.0 else (1.0 if u > 1.0 else u)
                    rx = dx - u * ex
                    ry = dy - u * ey
                    d2 = rx * rx + ry * ry
                    nearer = d2 < best[t]
                    best[t] = d2 if nearer else best[t]
                    bj[t] = s if nearer else bj[t]
                    bt[t] = u if nearer else bt[t]
                    brx[t] = rx if nearer else brx[t]
                    bry[t] = ry if nearer else bry[t]
            for t in range(npt):
                j = bj[t]
                if j < 0:
                    continue
                mx = snx[j]
                my = sny[j]
                u = bt[t]
                if u <= 0.0 or u >= 1.0:
                    rx = brx[t]
                    ry = bry[t]
                    rn = math.hypot(rx, ry)
                    if rn > 1e-12:
                        mx = rx / rn
                        my = ry / rn
                nx[t] = mx
                ny[t] = my
            for t in range(npt):
                mx = nx[t]
                my = ny[t]
                r = brx[t] * mx + bry[t] * my
                z = r / robust_scale
                rr[t] = r
                ww[t] = 1.0 / (1.0 + z * z)
                jj[t] = my * (qx[t] - px0) - mx * (qy[t] - py0)
            h00 = 0.0
            h01 = 0.0
            h02 = 0.0
            h11 = 0.0
            h12 = 0.0
            h22 = 0.0
            g0 = 0.0
            g1 = 0.0
            g2 = 0.0
            wsum = 0.0
            wrr = 0.0
            for t in range(npt):
                if bj[t] < 0:
                    continue
                mx = nx[t]
                my = ny[t]
                j2 = jj[t]
                r = rr[t]
                w = ww[t]
                w0 = mx * w
                w1 = my * w
                w2 = j2 * w
                g0 += w0 * r
                g1 += w1 * r
                g2 += w2 * r
                h00 += w0 * mx
                h01 += w0 * my
                h02 += w0 * j2
                h11 += w1 * my
                h12 += w1 * j2
                h22 += w2 * j2
                wsum += w
                wrr += w * r * r
            tr = (h00 + h11 + h22) / 3.0
            if tr < 1e-12:
                tr = 1e-12
            dmp = damping * tr
            A[0, 0] = h00 + dmp
            A[0, 1] = h01
            A[0, 2] = h02
            A[1, 0] = h01
            A[1, 1] = h11 + dmp
            A[1, 2] = h12
            A[2, 0] = h02
            A[2, 1] = h12
            A[2, 2] = h22 + dmp
            b[0] = g0
            b[1] = g1
            b[2] = g2
            solve3_into(A, b)
            poses[k, 0] = px0 - b[0]
            poses[k, 1] = py0 - b[1]
            poses[k, 2] = poses[k, 2] - b[2]
            rms[k] = math.sqrt(wrr / (wsum if wsum > 1e-12 else 1e-12))
    return poses, rms


@njit(cache=True, nogil=True)
def pose_iterations(
    P: np.ndarray,
    own: np.ndarray,
    segs: np.ndarray,
    seg_start: np.ndarray,
    seg_len: np.ndarray,
    pose0: np.ndarray,
    iterations: int,
    inlier_distance: float,
    robust_scale: float,
    damping: float,
    tol: float,
    prior: np.ndarray,
    prior_weight: float,
) -> tuple[np.ndarray, np.ndarray, float, int, int, bool]:
    """Kernel of :func:`service.core.pose.pose_from_matches`: the re-pairing Gauss-Newton
    loop. Pair ``own[i]``'s segments are rows ``seg_start[k] .. + seg_len[k] - 1`` of
    ``segs``; ``prior_weight`` 0 disables the prior. Returns ``(pose, H, rms, inliers,
    iterations, have_H)``."""
    N = P.shape[0]
    pose = pose0.copy()
    H = np.zeros((3, 3))
    have_h = False
    rms = np.inf
    n_in = 0
    it = 0
    A = np.empty((3, 3))
    gv = np.empty(3)
    ee_all = np.empty(segs.shape[0])
    for s in range(segs.shape[0]):
        ex = segs[s, 2] - segs[s, 0]
        ey = segs[s, 3] - segs[s, 1]
        v = ex * ex + ey * ey
        ee_all[s] = v if v > 1e-18 else 1e-18
    for it1 in range(iterations):
        it = it1 + 1
        c = math.cos(pose[2])
        sn = math.sin(pose[2])
        Hn = np.zeros((3, 3))
        g0 = 0.0
        g1 = 0.0
        g2 = 0.0
        sw = 0.0
        swrr = 0.0
        n_in = 0
        for i in range(N):
            k = own[i]
            px = P[i, 0]
            py = P[i, 1]
            qx = c * px - sn * py + pose[0]
            qy = sn * px + c * py + pose[1]
            best = np.inf
            bj = -1
            bt = 0.0
            for s in range(seg_start[k], seg_start[k] + seg_len[k]):
                ax = segs[s, 0]
                ay = segs[s, 1]
                ex = segs[s, 2] - ax
                ey = segs[s, 3] - ay
                dx = qx - ax
                dy = qy - ay
                t = (dx * ex + dy * ey) / ee_all[s]
                if t < 0.0:
                    t = 0.0
                elif t > 1.0:
                    t = 1.0
                rx = dx - t * ex
                ry = dy - t * ey
                d2 = rx * rx + ry * ry
                if d2 < best:
                    best = d2
                    bj = s
                    bt = t
            if bj < 0 or not (math.sqrt(best) <= inlier_distance):
                continue
            n_in += 1
            ax = segs[bj, 0]
            ay = segs[bj, 1]
            ex = segs[bj, 2] - ax
            ey = segs[bj, 3] - ay
            fx = ax + bt * ex
            fy = ay + bt * ey
            sq = math.sqrt(ee_all[bj])
            nx = -(ey / sq)
            ny = ex / sq
            if bt <= 0.0 or bt >= 1.0:
                rvx = qx - fx
                rvy = qy - fy
                rn = math.hypot(rvx, rvy)
                if rn > 1e-12:
                    nx = rvx / rn
                    ny = rvy / rn
            r = (qx - fx) * nx + (qy - fy) * ny
            z = r / robust_scale
            w = 1.0 / (1.0 + z * z)
            lx = qx - pose[0]
            ly = qy - pose[1]
            j0 = nx
            j1 = ny
            j2 = ny * lx - nx * ly
            w0 = j0 * w
            w1 = j1 * w
            w2 = j2 * w
            Hn[0, 0] += w0 * j0
            Hn[0, 1] += w0 * j1
            Hn[0, 2] += w0 * j2
            Hn[1, 1] += w1 * j1
            Hn[1, 2] += w1 * j2
            Hn[2, 2] += w2 * j2
            g0 += w0 * r
            g1 += w1 * r
            g2 += w2 * r
            sw += w
            swrr += w * r * r
        if n_in < 3:
            break
        Hn[1, 0] = Hn[0, 1]
        Hn[2, 0] = Hn[0, 2]
        Hn[2, 1] = Hn[1, 2]
        if prior_weight > 0.0:
            Hn[0, 0] += prior_weight
            Hn[1, 1] += prior_weight
            g0 += prior_weight * (pose[0] - prior[0])
            g1 += prior_weight * (pose[1] - prior[1])
        H = Hn
        have_h = True
        scale = (Hn[0, 0] + Hn[1, 1] + Hn[2, 2]) / 3.0
        if scale < 1e-12:
            scale = 1e-12
        for r1 in range(3):
            for r2 in range(3):
                A[r1, r2] = Hn[r1, r2] + (damping * scale if r1 == r2 else 0.0)
        gv[0] = g0
        gv[1] = g1
        gv[2] = g2
        d = solve3(A, gv)
        pose[0] = pose[0] - d[0]
        pose[1] = pose[1] - d[1]
        pose[2] = wrap(pose[2] - d[2])
        rms = math.sqrt(swrr / (sw if sw > 1e-12 else 1e-12))
        if math.hypot(d[0], d[1]) < tol and abs(d[2]) < tol:
            break
    return pose, H, rms, n_in, it, have_h
