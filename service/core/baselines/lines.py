"""Baseline 2 of the paper: localisation by line matching (after Cox; Lu & Milios; Gutmann).

Scan side: the scan's points are cut into clusters at range jumps, each cluster is split
recursively at the point farthest from the chord through its ends (split-and-merge), adjacent
pieces that fit one line are merged again, and every piece with enough points and length gets
a total-least-squares line fit (normal form ``n . p = r``) with outlier points dropped.

Map side: the map's polylines become line segments, consecutive (nearly) collinear edges
merged into one.

Matching, starting from the motion model's prior (:mod:`service.core.tracking.motion`: the previous
estimate moved by the odometry increment when the scan carries ``odom``, else the previous
estimate, as in the paper's experiment): each scan line, moved into
the map with the current pose, is associated with the nearest map line (Cox-style) that passes
an orientation gate, a perpendicular-distance gate and an overlap test; the pose then follows
from damped Gauss-Newton least squares of the point-to-line distances of all points of the
matched scan lines. Association and fit alternate a few times while the gates shrink.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from service.core import numeric
from service.core.baselines import (
    check_odom,
    check_pose,
    scan_points,
    transform_points,
)
from service.core.tracking.motion import Motion, MotionConfig
from service.core.types import Estimate, MapData, wrap_angle
from service.errors import LocalizationError


class LineConfig(BaseModel):
    """Parameters of :class:`LineLocalizer` (lengths in metres, angles in radians)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    break_distance: float = Field(
        0.25, gt=0.0, description="gap between consecutive scan points that starts a new cluster"
    )
    break_relative: float = Field(
        0.05, ge=0.0, description="extra allowed gap per metre of range (beams diverge)"
    )
    split_threshold: float = Field(
        0.04, gt=0.0, description="split a piece when a point is farther than this from its chord"
    )
    min_points: int = Field(6, ge=2, description="minimum points of a scan line")
    min_length: float = Field(0.3, gt=0.0, description="minimum length of a scan line")
    map_merge_angle: float = Field(
        math.radians(1.0), ge=0.0, description="merge consecutive map edges within this turn"
    )
    angle_gate_initial: float = Field(math.radians(15.0), gt=0.0, description="first iteration")
    angle_gate_final: float = Field(math.radians(5.0), gt=0.0, description="last iterations")
    dist_gate_initial: float = Field(0.5, gt=0.0, description="perpendicular gate, first")
    dist_gate_final: float = Field(0.2, gt=0.0, description="perpendicular gate, last")
    gate_decay: float = Field(0.7, gt=0.0, le=1.0, description="gate factor per iteration")
    overlap_margin: float = Field(
        0.3, ge=0.0, description="a scan line must overlap its map line up to this slack"
    )
    angle_weight: float = Field(
        1.0, ge=0.0, description="metres per radian when ranking candidate map lines"
    )
    max_iterations: int = Field(10, ge=1, le=100, description="association/fit rounds per scan")
    prior_weight: float = Field(
        1.0, ge=0.0, description="damping toward the start pose (keeps unobserved axes fixed)"
    )
    tol_translation: float = Field(1e-4, gt=0.0, description="convergence: step below (m)")
    tol_rotation: float = Field(1e-4, gt=0.0, description="convergence: step below (rad)")
    tracking_min_explained: float = Field(
        0.3, ge=0.0, le=1.0, description="matched fraction of scan points to say tracking"
    )
    tracking_max_rms: float = Field(0.05, gt=0.0, description="rms point-to-line distance")
    range_max: float = Field(math.inf, gt=0.0, description="ignore returns beyond this range")
    use_odometry: bool = Field(
        True,
        description="seed each scan with the odometry increment when the scan carries odom "
        "(service.core.tracking.motion, shared by every method); without odometry -- the paper's "
        "experiment -- the start value is the previous estimate",
    )


@dataclass(frozen=True)
class LineSegment:
    """A fitted line ``n . p = r`` with ``n = (cos alpha, sin alpha)``, ``r >= 0`` (metres),
    its end points ``p0``/``p1`` (projections of the extreme points) and the indices of the
    points that support it (into the point array it was extracted from)."""

    alpha: float
    r: float
    p0: np.ndarray
    p1: np.ndarray
    indices: np.ndarray

    @property
    def length(self) -> float:
        """Segment length in metres."""
        return float(np.hypot(*(self.p1 - self.p0)))


def fit_line(points: np.ndarray) -> tuple[float, float, np.ndarray]:
    """Total least squares line through ``(k, 2)`` points.

    Returns ``(alpha, r, residuals)``: normal angle, distance from the origin (``>= 0``) and
    the signed point-to-line distances.
    """
    cx, cy = points[:, 0].mean(), points[:, 1].mean()
    dx, dy = points[:, 0] - cx, points[:, 1] - cy
    sxx, syy, sxy = numeric.dot(dx, dx), numeric.dot(dy, dy), numeric.dot(dx, dy)
    # Direction of largest spread (closed-form 2x2 eigenvector); the normal is perpendicular.
    alpha = 0.5 * math.atan2(2.0 * sxy, sxx - syy) + 0.5 * math.pi
    n = np.array([math.cos(alpha), math.sin(alpha)])
    r = float(n[0] * cx + n[1] * cy)
    if r < 0.0:
        n, r = -n, -r
    return numeric.atan2(n[1], n[0]), r, numeric.matvec(points, n) - r


def _segment_from(points: np.ndarray, idx: np.ndarray, split_threshold: float) -> LineSegment:
    alpha, r, res = fit_line(points[idx])
    ok = np.abs(res) <= split_threshold
    if ok.sum() >= 2 and not ok.all():  # drop stray points (e.g. at corners) and refit
        idx = idx[ok]
        alpha, r, res = fit_line(points[idx])
    n = np.array([math.cos(alpha), math.sin(alpha)])
    tdir = np.array([-n[1], n[0]])
    s = numeric.matvec(points[idx], tdir)
    foot = r * n
    return LineSegment(alpha, r, foot + s.min() * tdir, foot + s.max() * tdir, idx)


def extract_lines(
    points: np.ndarray, config: LineConfig | None = None, closed: bool = False
) -> list[LineSegment]:
    """Split-and-merge line extraction from ordered scan points ``(n, 2)`` (any frame, m).

    Points must be in beam order. ``closed`` says the scan covers a full turn, so the last
    point neighbours the first (extraction then starts at the widest gap). Returns the lines
    with at least ``min_points`` points and ``min_length`` length, in scan order; their
    ``indices`` refer to ``points``.
    """
    cfg = config or LineConfig()
    n = len(points)
    if n < 2:
        return []
    if closed and n > 2:
        gaps = np.hypot(*(np.roll(points, -1, axis=0) - points).T)
        shift = (int(np.argmax(gaps)) + 1) % n
        if shift:
            lines = extract_lines(np.roll(points, -shift, axis=0), cfg, closed=False)
            return [
                LineSegment(ln.alpha, ln.r, ln.p0, ln.p1, (ln.indices + shift) % n) for ln in lines
            ]
    gaps = np.hypot(*np.diff(points, axis=0).T)
    rng = np.hypot(points[:, 0], points[:, 1])
    limit = cfg.break_distance + cfg.break_relative * np.maximum(rng[:-1], rng[1:])
    cuts = np.flatnonzero(gaps > limit) + 1
    bounds = np.concatenate([[0], cuts, [n]])
    pieces: list[tuple[int, int]] = []  # half-open index ranges, in order
    for a, b in itertools.pairwise(bounds):
        if b - a < 2:
            continue
        stack = [(int(a), int(b))]
        out: list[tuple[int, int]] = []
        while stack:
            i, j = stack.pop()
            p, q = points[i], points[j - 1]
            chord = q - p
            length = math.hypot(*chord)
            seg = points[i:j]
            if length < 1e-12:
                dist = np.hypot(*(seg - p).T)
            else:
                dist = np.abs(chord[0] * (seg[:, 1] - p[1]) - chord[1] * (seg[:, 0] - p[0]))
                dist /= length
            k = int(np.argmax(dist))
            if dist[k] > cfg.split_threshold and 0 < k < j - i - 1:
                stack.append((i + k, j))  # processed after the left part (LIFO)
                stack.append((i, i + k + 1))
            else:
                out.append((i, j))
        # Neighbouring pieces share their split point; the refit drops it where it does not fit.
        pieces.extend(_merge(points, out, cfg))
    lines = []
    for i, j in pieces:
        if j - i < cfg.min_points:
            continue
        seg = _segment_from(points, np.arange(i, j), cfg.split_threshold)
        if len(seg.indices) >= cfg.min_points and seg.length >= cfg.min_length:
            lines.append(seg)
    return lines


def _merge(points: np.ndarray, pieces: list[tuple[int, int]], cfg: LineConfig):
    """Merge neighbouring pieces whose union still fits one line within the threshold."""
    merged: list[tuple[int, int]] = []
    for i, j in pieces:
        if merged:
            a, b = merged[-1]
            lo, hi = a, max(b, j)
            if hi - lo >= 3:
                _, _, res = fit_line(points[lo:hi])
                if np.max(np.abs(res)) <= cfg.split_threshold:
                    merged[-1] = (lo, hi)
                    continue
        merged.append((i, j))
    return merged


def map_lines(map_data: MapData, merge_angle: float = math.radians(1.0)) -> np.ndarray:
    """Map line segments ``(m, 4)`` ``[x0, y0, x1, y1]`` (metres, map frame).

    Consecutive polyline edges that turn by less than ``merge_angle`` are merged into one
    segment (also across the closing vertex of a closed ring); zero-length edges are dropped.
    """
    out: list[np.ndarray] = []
    for poly in map_data.polylines:
        pts = np.asarray(poly, dtype=np.float64)
        keep = np.concatenate([[True], np.hypot(*np.diff(pts, axis=0).T) > 1e-9])
        pts = pts[keep]
        if len(pts) < 2:
            continue
        closed = len(pts) > 3 and np.allclose(pts[0], pts[-1])
        d = np.diff(pts, axis=0)
        heading = numeric.atan2(d[:, 1], d[:, 0])
        turn = np.abs(wrap_angle(np.diff(heading))) if len(d) > 1 else np.array([])
        # Vertex k (1..len-2) is kept iff the path turns there.
        corner = np.concatenate([[True], turn >= merge_angle, [True]])
        verts = pts[corner]
        segs = np.hstack([verts[:-1], verts[1:]])
        if closed and len(segs) > 1:
            first, last = segs[0], segs[-1]
            h0 = math.atan2(first[3] - first[1], first[2] - first[0])
            h1 = math.atan2(last[3] - last[1], last[2] - last[0])
            if abs(wrap_angle(h0 - h1)) < merge_angle:
                segs = np.vstack([[[*last[:2], *first[2:]]], segs[1:-1]])
        out.append(segs)
    if not out:
        raise LocalizationError(f"map {map_data.map_id!r} has no non-degenerate edge")
    return np.vstack(out)


class LineLocalizer:
    """Line-matching tracking (the paper's "line-based" baseline). Needs a start pose.

    Implements :class:`service.core.types.Localizer`. Poses are ``[x m, y m, theta rad]`` in
    the map frame.
    """

    method = "lines"

    def __init__(
        self,
        map_data: MapData,
        initial_pose: np.ndarray | None,
        config: LineConfig | None = None,
    ) -> None:
        if config is not None and not isinstance(config, LineConfig):
            raise LocalizationError(f"lines config must be LineConfig, got {type(config).__name__}")
        self.config = config or LineConfig()
        self.map_data = map_data
        self._pose = check_pose(initial_pose, self.method)
        self.motion = Motion(MotionConfig(use_odometry=self.config.use_odometry, extrapolate=False))
        segs = map_lines(map_data, self.config.map_merge_angle)
        self.map_segments = segs
        d = segs[:, 2:] - segs[:, :2]
        self._len = np.hypot(d[:, 0], d[:, 1])
        self._dir = d / self._len[:, None]
        self._normal = np.column_stack([-self._dir[:, 1], self._dir[:, 0]])
        self._offset = np.einsum("ij,ij->i", self._normal, segs[:, :2])  # n . p = offset
        self._heading = numeric.atan2(self._dir[:, 1], self._dir[:, 0])
        self._start_t = np.einsum("ij,ij->i", self._dir, segs[:, :2])

    @property
    def pose(self) -> np.ndarray | None:
        """Last estimate ``[x, y, theta]`` (map frame), a copy."""
        return self._pose.copy()

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Restart tracking from ``initial_pose``; ``None`` raises (no global localisation).
        ``odom``: odometry pose at ``initial_pose`` (the next increment starts from it)."""
        self._pose = check_pose(initial_pose, self.method)
        self.motion.reset(odom)

    def _associate(
        self, lines: list[LineSegment], pose: np.ndarray, angle_gate: float, dist_gate: float
    ) -> np.ndarray:
        """Index of the nearest gated map line per scan line (``-1``: none), Cox-style."""
        cfg = self.config
        ends = transform_points(pose, np.vstack([np.vstack([ln.p0, ln.p1]) for ln in lines]))
        a, b = ends[0::2], ends[1::2]  # (k, 2) each
        sd = b - a
        ang = numeric.atan2(sd[:, 1], sd[:, 0])
        dang = np.abs(wrap_angle(2.0 * (self._heading[None, :] - ang[:, None]))) / 2.0
        mid = 0.5 * (a + b)
        perp = np.abs(numeric.matmul(mid, self._normal.T) - self._offset[None, :])
        # Overlap along each map line: projected scan interval against [0, length].
        t0 = numeric.matmul(a, self._dir.T) - self._start_t[None, :]
        t1 = numeric.matmul(b, self._dir.T) - self._start_t[None, :]
        lo, hi = np.minimum(t0, t1), np.maximum(t0, t1)
        m = cfg.overlap_margin
        ok = (dang < angle_gate) & (perp < dist_gate) & (hi > -m) & (lo < self._len[None, :] + m)
        cost = np.where(ok, perp + cfg.angle_weight * dang, np.inf)
        best = np.argmin(cost, axis=1)
        return np.where(ok.any(axis=1), best, -1)

    def update(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None = None
    ) -> Estimate:
        """Match one scan (ranges m, NaN = no return; angles rad, robot frame)."""
        cfg = self.config
        odom_v = check_odom(odom)
        pts = scan_points(ranges, angles, cfg.range_max)
        pose = self.motion.predict(self._pose, odom_v).pose
        a = np.asarray(angles, dtype=np.float64)
        span = float(a.max() - a.min()) if a.size > 1 else 0.0
        step = span / (a.size - 1) if a.size > 1 else 0.0
        lines = extract_lines(pts, cfg, closed=span + 1.5 * step >= 2.0 * math.pi)
        extras = {"points": float(len(pts)), "lines": float(len(lines)), "matched": 0.0}
        if not lines:
            self._pose = pose
            return Estimate(pose=pose.copy(), status="lost", score=0.0, extras=extras)
        start = pose.copy()
        angle_gate, dist_gate = cfg.angle_gate_initial, cfg.dist_gate_initial
        assoc = np.full(len(lines), -1)
        for _ in range(cfg.max_iterations):
            assoc = self._associate(lines, pose, angle_gate, dist_gate)
            new = self._fit(pts, lines, assoc, pose, start)
            at_final = angle_gate <= cfg.angle_gate_final and dist_gate <= cfg.dist_gate_final
            angle_gate = max(cfg.angle_gate_final, angle_gate * cfg.gate_decay)
            dist_gate = max(cfg.dist_gate_final, dist_gate * cfg.gate_decay)
            if new is None:
                continue
            dt = float(np.hypot(new[0] - pose[0], new[1] - pose[1]))
            dr = abs(float(wrap_angle(new[2] - pose[2])))
            pose = new
            if at_final and dt < cfg.tol_translation and dr < cfg.tol_rotation:
                break
        pose[2] = wrap_angle(pose[2])
        assoc = self._associate(lines, pose, cfg.angle_gate_final, cfg.dist_gate_final)
        matched = assoc >= 0
        extras["matched"] = float(matched.sum())
        if not matched.any():
            self._pose = pose
            return Estimate(pose=pose.copy(), status="lost", score=0.0, extras=extras)
        idx = np.concatenate([lines[k].indices for k in np.flatnonzero(matched)])
        mids = np.concatenate(
            [np.full(len(lines[k].indices), assoc[k]) for k in np.flatnonzero(matched)]
        )
        q = transform_points(pose, pts[idx])
        res = np.einsum("ij,ij->i", q, self._normal[mids]) - self._offset[mids]
        rms = float(np.sqrt(np.mean(res**2)))
        explained = float(len(idx) / max(len(pts), 1))
        headings = np.array([lines[k].alpha for k in np.flatnonzero(matched)])
        spread = np.abs(wrap_angle(2.0 * (headings[:, None] - headings[None, :]))) / 2.0
        constrained = bool(spread.max() > math.radians(20.0)) if len(headings) > 1 else False
        tracking = (
            constrained and explained >= cfg.tracking_min_explained and rms <= cfg.tracking_max_rms
        )
        quality = max(0.0, 1.0 - rms / cfg.dist_gate_final)
        extras.update({"rms_m": rms, "explained": explained})
        self._pose = pose
        return Estimate(
            pose=pose.copy(),
            status="tracking" if tracking else "lost",
            score=float(np.clip(explained * quality, 0.0, 1.0)),
            explained=explained,
            extras=extras,
        )

    def _fit(
        self,
        pts: np.ndarray,
        lines: list[LineSegment],
        assoc: np.ndarray,
        pose: np.ndarray,
        start: np.ndarray,
    ) -> np.ndarray | None:
        """Damped Gauss-Newton on point-to-line distances; ``None`` if nothing is matched."""
        sel = np.flatnonzero(assoc >= 0)
        if sel.size == 0:
            return None
        idx = np.concatenate([lines[k].indices for k in sel])
        mid = np.concatenate([np.full(len(lines[k].indices), assoc[k]) for k in sel])
        p = pts[idx]
        n = self._normal[mid]
        off = self._offset[mid]
        x = pose.copy()
        mu = self.config.prior_weight
        # Rotation damping scaled by the squared scan radius so it is in metres^2 too.
        rad2 = float(np.mean(np.sum(p**2, axis=1))) + 1e-6
        damp = np.diag([mu, mu, mu * rad2])
        for _ in range(3):
            c, s = math.cos(x[2]), math.sin(x[2])
            rx = c * p[:, 0] - s * p[:, 1]
            ry = s * p[:, 0] + c * p[:, 1]
            e = n[:, 0] * (rx + x[0]) + n[:, 1] * (ry + x[1]) - off
            J = np.column_stack([n[:, 0], n[:, 1], -n[:, 0] * ry + n[:, 1] * rx])
            prior = x - start
            prior[2] = math.remainder(prior[2], 2.0 * math.pi)
            A = numeric.matmul(J.T, J) + damp
            g = numeric.matvec(J.T, e) + numeric.matvec(damp, prior)
            step = numeric.solve(A, -g)
            x = x + step
            x[2] = math.remainder(x[2], 2.0 * math.pi)
            if np.hypot(step[0], step[1]) < 1e-6 and abs(step[2]) < 1e-7:
                break
        return x
