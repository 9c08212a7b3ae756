"""Exact 2D ray casting against line segments (numpy only).

Used by the laser simulator (against the true world) and by the localisation core to compute a
map's "abstract sensor reading" from a hypothesised pose.

Frames: segments and poses are in the map frame (metres); a pose is ``[x, y, theta]`` with
theta in radians CCW from the map x axis; beam angles are in the robot frame (radians, CCW from
the robot's forward x axis) and the sensor sits at the robot origin.

Algorithm: segments farther than ``max_range`` from the sensor are dropped; every remaining
segment is turned into the interval of bearings it subtends as seen from the sensor, and the
beams whose angle lies in that interval are found with a binary search over the sorted beam
angles. Only those (beam, segment) pairs are intersected exactly, and the nearest hit per beam
is kept. The cost is therefore proportional to the number of beam/segment pairs that can
actually intersect, not to beams x segments.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import raycast as raycast_kernels
from service.errors import LocalizationError

_TWO_PI = 2.0 * np.pi
# Angular slack (rad) added around each segment's bearing interval; the exact test decides.
_ANG_EPS = 1e-9
# Relative tolerance on the segment parameter u so that rays through a shared vertex hit.
_U_EPS = 1e-12
# Distinct beam sets whose bearing order a caster keeps (RayCaster._beam_order).
_ORDER_CACHE = 256
# The compiled kernel's measured ranges when there are none (it reads them only with tol >= 0).
_NO_RANGES = np.zeros(0)


class _Spans(NamedTuple):
    """Per segment near a pose (:meth:`RayCaster._spans`): its pose ``owner``, start ``a``
    and direction ``e`` ``(m, 2)``; that pose's position ``px``, ``py`` (per segment); the
    runs ``[i0, i1)`` and ``[0, j1)`` of beam positions in ``order`` (beams by bearing)."""

    owner: np.ndarray
    a: np.ndarray
    e: np.ndarray
    px: np.ndarray
    py: np.ndarray
    i0: np.ndarray
    i1: np.ndarray
    j1: np.ndarray
    order: np.ndarray


class RayCaster:
    """Nearest-hit ray casting against a fixed set of segments.

    ``segments`` is an ``(s, 4)`` array ``[x0, y0, x1, y1]`` in metres (map frame). Zero-length
    and non-finite segments are rejected with :class:`LocalizationError`.
    """

    def __init__(self, segments: np.ndarray) -> None:
        seg = np.asarray(segments, dtype=np.float64)
        if seg.ndim != 2 or seg.shape[1] != 4:
            raise LocalizationError(f"segments: expected shape (s, 4), got {seg.shape}")
        if not np.all(np.isfinite(seg)):
            raise LocalizationError("segments: non-finite coordinate")
        length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
        seg = seg[length > 0.0]
        self._seg = np.ascontiguousarray(seg)
        self._a = self._seg[:, 0:2]
        self._e = self._seg[:, 2:4] - self._seg[:, 0:2]
        self._ee = np.einsum("ij,ij->i", self._e, self._e)
        self._a_c = np.ascontiguousarray(self._a)  # the kernels' copy
        self._orders: dict[bytes, tuple[float, np.ndarray, np.ndarray]] = {}

    @property
    def segments(self) -> np.ndarray:
        """The (non-degenerate) segments, ``(s, 4)`` metres in the map frame."""
        return self._seg

    def _distances(self, p: np.ndarray) -> np.ndarray:
        """Euclidean distance (m) from point ``p`` to every segment."""
        ap = p - self._a
        t = np.clip(np.einsum("ij,ij->i", ap, self._e) / self._ee, 0.0, 1.0)
        d = ap - t[:, None] * self._e
        return np.hypot(d[:, 0], d[:, 1])

    def cast(self, pose: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
        """Range (m) along each beam to the nearest segment, NaN where nothing is within
        ``max_range``.

        ``pose`` is ``[x, y, theta]`` in the map frame; ``angles`` (n,) are beam angles in the
        robot frame (any order, any values). A ray that starts on a segment returns 0. Rays
        exactly collinear with a segment do not hit that segment (its neighbours in a closed
        ring catch such rays).
        """
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (3,):
            raise LocalizationError(f"pose: expected 3 finite values, got shape {pose.shape}")
        return self.cast_many(pose.reshape(1, 3), angles, max_range)[0]  # checks finiteness

    def cast_many(self, poses: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
        """:meth:`cast` from each of ``poses`` ``(P, 3)`` with the same ``angles``, ``(P, n)``:
        one pass over all poses' beam / segment pairs (each range is computed by the same
        operations as for its pose alone)."""
        poses = np.asarray(poses, dtype=np.float64)
        best, _ = self._nearest(poses, angles, max_range, None, -1.0)  # checks the arguments
        return np.where(np.isinf(best), np.nan, best)  # no hit: NaN

    def cast_layered(
        self,
        pose: np.ndarray,
        angles: np.ndarray,
        ranges: np.ndarray,
        tol: float,
        max_range: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`cast`, and per beam whether the measured ``ranges`` (NaN: none) lie within
        ``tol`` of *any* segment the beam crosses, not only the nearest: a return from a
        surface the map holds behind another one (the laser saw past a mapped object)."""
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise LocalizationError(f"pose: expected 3 finite values, got shape {pose.shape}")
        r = np.asarray(ranges, dtype=np.float64)
        n = np.shape(angles)[0]
        if r.shape != (n,):
            raise LocalizationError(f"ranges: expected shape ({n},), got {r.shape}")
        best, on_map = self._nearest(pose.reshape(1, 3), angles, max_range, r, tol)
        return np.where(np.isinf(best[0]), np.nan, best[0]), on_map

    def _nearest(
        self,
        poses: np.ndarray,
        angles: np.ndarray,
        max_range: float,
        ranges: np.ndarray | None,
        tol: float,
    ) -> tuple[np.ndarray, np.ndarray]:
        """The nearest hit per pose and beam, ``(P, n)`` (``inf``: none), and, with
        ``ranges`` (one pose), per beam whether any hit lies within ``tol`` of its range;
        checks the arguments. The compiled kernel walks the spans of :meth:`_spans` pair by
        pair (:func:`service.core.kernels.raycast.nearest_hits`); without numba the pairs
        are built as arrays (:meth:`_pairs`). Both give the same bits."""
        ang = self._check(poses, angles, max_range)
        n_pose, n = poses.shape[0], ang.shape[0]
        best = np.full((n_pose, n), np.inf)
        on_map = np.zeros(n, dtype=bool)
        if n == 0 or n_pose == 0 or self._seg.shape[0] == 0:
            return best, on_map
        if kernels.HAVE_NUMBA:
            self._nearest_compiled(poses, ang, max_range, ranges, tol, best, on_map)
            return best, on_map
        spans = self._spans(poses, ang, max_range)
        if spans is None:
            return best, on_map
        pairs = self._pairs(poses, ang, max_range, spans)
        if pairs is None:
            return best, on_map
        pair_pose, pair_beam, t = pairs
        # Nearest hit per beam; a pose's pairs keep their order, so each beam sees its
        # candidates in the same order as when its pose is cast alone.
        flat = best.reshape(-1)
        np.minimum.at(flat, pair_pose * n + pair_beam, t)
        if ranges is not None:
            close = np.abs(t - ranges[pair_beam]) <= tol  # NaN ranges compare False
            on_map[pair_beam[close]] = True
        return best, on_map

    def _nearest_compiled(
        self,
        poses: np.ndarray,
        ang: np.ndarray,
        max_range: float,
        ranges: np.ndarray | None,
        tol: float,
        best: np.ndarray,
        on_map: np.ndarray,
    ) -> None:
        """:meth:`_nearest` by the kernels of :mod:`service.core.kernels.raycast` (the same
        steps as :meth:`_spans` and :meth:`_pairs`; the bearings' ``arctan2`` in numpy)."""
        idx, owner, touching, ends = raycast_kernels.near_segments(
            self._a_c, self._e, self._ee, poses, float(max_range)
        )
        if idx.shape[0] == 0:
            return
        bearing0 = numeric.atan2(ends[1], ends[0])
        bearing1 = numeric.atan2(ends[3], ends[2])
        base, rel_sorted, order = self._beam_order(ang)
        world = ang[None, :] + poses[:, 2][:, None]
        raycast_kernels.nearest_hits(
            self._a_c,
            self._e,
            idx,
            owner,
            touching,
            bearing0,
            bearing1,
            poses,
            base,
            rel_sorted,
            order,
            np.cos(world),
            np.sin(world),
            float(max_range),
            _ANG_EPS,
            _U_EPS,
            _NO_RANGES if ranges is None else ranges,
            float(tol) if ranges is not None else -1.0,
            best,
            on_map,
        )

    def _beam_order(self, ang: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """The first beam's angle, the beams' angles relative to it folded into ``[0, 2pi)``
        and sorted, and that order (both paths of :meth:`_nearest` use them). Kept per distinct
        ``ang`` (at most :data:`_ORDER_CACHE` of them): the core casts the same beams of a
        keyframe or scan from many poses."""
        key = ang.tobytes()
        hit = self._orders.get(key)
        if hit is not None:
            return hit
        base = ang[0]
        rel = np.mod(ang - base, _TWO_PI)
        order = np.argsort(rel, kind="stable")
        rel_sorted = rel[order]
        rel_sorted.setflags(write=False)  # shared by every cast of these beams
        order.setflags(write=False)
        out = (float(base), rel_sorted, order)
        if len(self._orders) >= _ORDER_CACHE:
            self._orders.clear()
        self._orders[key] = out
        return out

    @staticmethod
    def _check(poses: np.ndarray, angles: np.ndarray, max_range: float) -> np.ndarray:
        """The beam angles as float64, after checking the arguments of a cast."""
        ang = np.asarray(angles, dtype=np.float64)
        # (the arrays' own .all(): these run for every cast of a search)
        if poses.ndim != 2 or poses.shape[1] != 3 or not np.isfinite(poses).all():
            raise LocalizationError(f"poses: expected (P, 3) finite values, got {poses.shape}")
        if ang.ndim != 1:
            raise LocalizationError(f"angles: expected a 1-D array, got shape {ang.shape}")
        if not np.isfinite(ang).all():
            raise LocalizationError("angles: non-finite value")
        if not (np.isfinite(max_range) and max_range > 0.0):
            raise LocalizationError(f"max_range must be finite and > 0, got {max_range}")
        return ang

    def _spans(self, poses: np.ndarray, ang: np.ndarray, max_range: float) -> _Spans | None:
        """The segments within ``max_range`` of each pose and, per segment, the run of beams
        (positions in bearing order) its bearing interval covers (``None``: no segment near
        any pose; the numpy reference of the kernels)."""
        n_pose = poses.shape[0]

        # The segments within range of each pose, all poses' one after the other; per segment
        # its pose's position and heading.
        near = []
        dists = []
        for k in range(n_pose):
            dist = self._distances(poses[k, :2])
            keep = np.nonzero(dist <= max_range)[0]
            near.append(keep)
            dists.append(dist[keep])
        counts_k = [len(x) for x in near]
        if sum(counts_k) == 0:
            return None
        idx = np.concatenate(near)
        owner = np.repeat(np.arange(n_pose), counts_k)
        a = self._a[idx]
        e = self._e[idx]
        b = a + e
        touching = np.concatenate(dists) <= 1e-12
        px = poses[owner, 0]
        py = poses[owner, 1]

        # Beam angles relative to the first beam, folded into [0, 2pi), sorted.
        base, rel_sorted, order = self._beam_order(ang)

        # Bearing interval of each segment in the same relative frame.
        off = (poses[:, 2] + base)[owner]
        b0 = numeric.atan2(a[:, 1] - py, a[:, 0] - px) - off
        b1 = numeric.atan2(b[:, 1] - py, b[:, 0] - px) - off
        delta = np.mod(b1 - b0 + np.pi, _TWO_PI) - np.pi  # signed span in (-pi, pi]
        lo = np.where(delta >= 0.0, b0, b1)
        span = np.abs(delta)
        lo = np.mod(lo, _TWO_PI)
        # A segment passing (nearly) through the sensor subtends ~pi or is degenerate in
        # bearing; give it every beam and let the exact test decide.
        through = (span >= np.pi - 1e-9) | touching
        lo = np.where(through, 0.0, lo)
        hi = np.where(through, _TWO_PI, lo + span)

        # Interval [lo, hi] may exceed 2pi: split into [lo, min(hi, 2pi)] and [0, hi - 2pi].
        i0 = np.searchsorted(rel_sorted, lo - _ANG_EPS, side="left")
        i1 = np.searchsorted(rel_sorted, np.minimum(hi, _TWO_PI) + _ANG_EPS, side="right")
        j1 = np.searchsorted(rel_sorted, hi - _TWO_PI + _ANG_EPS, side="right")
        j1 = np.where(hi > _TWO_PI, j1, 0)
        return _Spans(owner, a, e, px, py, i0, i1, j1, order)

    def _pairs(
        self, poses: np.ndarray, ang: np.ndarray, max_range: float, spans: _Spans
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """Every (pose, beam, segment) intersection within ``max_range`` of ``spans`` (the
        numpy reference of the kernel): the pose and beam index and the range ``t`` of each
        (``None``: none)."""
        owner, a, e, px, py = spans.owner, spans.a, spans.e, spans.px, spans.py
        i0, i1, j1, order = spans.i0, spans.i1, spans.j1, spans.order
        seg_idx = np.arange(a.shape[0])
        starts = np.concatenate([i0, np.zeros_like(j1)])
        counts = np.concatenate([np.maximum(i1 - i0, 0), j1])
        owners = np.concatenate([seg_idx, seg_idx])
        total = int(counts.sum())
        if total == 0:
            return None
        pair_seg = np.repeat(owners, counts)
        # Position within each run: global index minus the run's start offset.
        run_start = np.repeat(np.cumsum(counts) - counts, counts)
        pair_pos = np.repeat(starts, counts) + (np.arange(total) - run_start)
        pair_beam = order[pair_pos]
        pair_pose = owner[pair_seg]

        # Exact intersection: p + t*d = a + u*e.
        world_ang = ang[pair_beam] + poses[pair_pose, 2]
        dx = np.cos(world_ang)
        dy = np.sin(world_ang)
        ex = e[pair_seg, 0]
        ey = e[pair_seg, 1]
        wx = a[pair_seg, 0] - px[pair_seg]
        wy = a[pair_seg, 1] - py[pair_seg]
        den = dx * ey - dy * ex
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (wx * ey - wy * ex) / den
            u = (wx * dy - wy * dx) / den
        ok = (den != 0.0) & (t >= 0.0) & (t <= max_range) & (u >= -_U_EPS) & (u <= 1.0 + _U_EPS)
        if not np.any(ok):
            return None
        return pair_pose[ok], pair_beam[ok], t[ok]
