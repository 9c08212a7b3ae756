"""Baseline 1 of the paper: Iterative Closest Point against an occupancy grid (Besl & McKay).

The map's polylines are rasterised into an occupancy grid of ``cell_size`` (paper: 50 mm)
cells: every cell whose interior a map segment passes through is occupied. A Euclidean
distance transform (``scipy.ndimage.distance_transform_edt`` with ``return_indices``),
computed once per map over the map's bounding box plus a margin, gives for every cell the
centre of its nearest occupied cell, so the closest-point query of ICP is a table lookup.

Each :meth:`ICPLocalizer.update` starts from the motion model's prior
(:mod:`service.core.tracking.motion`, shared by every method): the previous estimate moved by the
odometry increment when the scan carries ``odom``, else the previous estimate itself (the
paper's experiment sends no odometry), transforms the scan points into the map, pairs each
with its nearest occupied cell centre, rejects outliers with a distance gate that shrinks
geometrically over the iterations followed by trimming of the worst pairs, and solves the
closed-form 2D rigid least squares problem; this repeats until the pose change drops below
the tolerances.
"""

from __future__ import annotations

import math

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage

from service.core import numeric
from service.core.baselines import (
    check_odom,
    check_pose,
    scan_points,
)
from service.core.tracking.motion import Motion, MotionConfig
from service.core.types import Estimate, MapData, wrap_angle
from service.errors import LocalizationError


class ICPConfig(BaseModel):
    """Parameters of :class:`ICPLocalizer` (lengths in metres, angles in radians)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    cell_size: float = Field(0.05, gt=0.0, le=1.0, description="grid cell edge (paper: 50 mm)")
    margin: float = Field(1.0, ge=0.0, le=50.0, description="grid padding around the map")
    max_iterations: int = Field(40, ge=1, le=500, description="ICP iterations per scan")
    gate_initial: float = Field(1.0, gt=0.0, description="pair distance gate, first iteration")
    gate_final: float = Field(0.2, gt=0.0, description="smallest pair distance gate")
    gate_decay: float = Field(0.75, gt=0.0, le=1.0, description="gate factor per iteration")
    trim_fraction: float = Field(
        1.0,
        gt=0.0,
        le=1.0,
        description="fraction of gated pairs kept, closest first (1: gate only; trimming lost "
        "tracking on the office tour, see docs/experiment)",
    )
    tol_translation: float = Field(1e-4, gt=0.0, description="convergence: step below (m)")
    tol_rotation: float = Field(1e-4, gt=0.0, description="convergence: step below (rad)")
    min_points: int = Field(10, ge=3, description="fewer valid pairs: keep the old pose, lost")
    tracking_min_inliers: float = Field(
        0.5, ge=0.0, le=1.0, description="inlier fraction (within gate_final) to say tracking"
    )
    tracking_max_rms: float = Field(0.1, gt=0.0, description="rms pair distance to say tracking")
    range_max: float = Field(math.inf, gt=0.0, description="ignore returns beyond this range")
    use_odometry: bool = Field(
        True,
        description="seed each scan with the odometry increment when the scan carries odom "
        "(service.core.tracking.motion, shared by every method); without odometry -- the paper's "
        "experiment -- the start value is the previous estimate",
    )


def rasterize_segments(
    segments: np.ndarray, origin: np.ndarray, cell_size: float, shape: tuple[int, int]
) -> np.ndarray:
    """Occupancy grid ``(ny, nx)`` bool with every cell a segment passes through set.

    ``segments`` is ``(s, 4)`` ``[x0, y0, x1, y1]`` in metres; cell ``(iy, ix)`` covers
    ``origin + [ix, iy] * cell_size`` to ``origin + [ix + 1, iy + 1] * cell_size``. The
    traversal is exact: the segment is cut at every grid line it crosses and the cell holding
    the midpoint of each piece is marked, so a cell is marked iff the segment passes through
    its interior; a piece running exactly along a grid line marks the cells on both sides
    (a degenerate, zero-length segment marks the cell holding it). Cells outside ``shape``
    are ignored.
    """
    ny, nx = shape
    grid = np.zeros(shape, dtype=bool)
    segs = np.asarray(segments, dtype=np.float64).reshape(-1, 4)
    for x0, y0, x1, y1 in segs:
        g0 = (np.array([x0, y0]) - origin) / cell_size
        g1 = (np.array([x1, y1]) - origin) / cell_size
        d = g1 - g0
        ts = [np.array([0.0, 1.0])]
        for k in range(2):
            if d[k] != 0.0:
                lo, hi = sorted((g0[k], g1[k]))
                lines = np.arange(math.floor(lo) + 1, math.ceil(hi), dtype=np.float64)
                ts.append((lines - g0[k]) / d[k])
        t = np.unique(np.concatenate(ts))
        t = t[(t >= 0.0) & (t <= 1.0)]
        mids = (t[:-1] + t[1:]) * 0.5
        # A zero-length segment marks the cell holding it.
        pts = g0 + mids[:, None] * d if mids.size else g0[None, :]
        cells = np.floor(pts).astype(np.int64)
        # A piece lying exactly on a grid line borders two cells: mark both.
        on_line = pts == np.floor(pts)
        extra = [cells[on_line[:, k]] - np.eye(2, dtype=np.int64)[k] for k in range(2)]
        cells = np.vstack([cells, *extra])
        ok = (cells[:, 0] >= 0) & (cells[:, 0] < nx) & (cells[:, 1] >= 0) & (cells[:, 1] < ny)
        cells = cells[ok]
        grid[cells[:, 1], cells[:, 0]] = True
    return grid


class DistanceGrid:
    """Occupancy grid of a map plus, per cell, the centre of the nearest occupied cell.

    Built once per map (cost: one distance transform over the padded bounding box).
    """

    def __init__(self, map_data: MapData, cell_size: float = 0.05, margin: float = 1.0) -> None:
        xmin, ymin, xmax, ymax = map_data.bounds()
        self.cell_size = float(cell_size)
        self.origin = np.array([xmin - margin, ymin - margin], dtype=np.float64)
        nx = math.ceil((xmax - xmin + 2.0 * margin) / cell_size) + 1
        ny = math.ceil((ymax - ymin + 2.0 * margin) / cell_size) + 1
        if nx * ny > 40_000_000:
            raise LocalizationError(
                f"map {map_data.map_id!r} needs a {nx}x{ny} ICP grid at {cell_size} m cells; "
                "too large (limit 4e7 cells)"
            )
        self.shape = (ny, nx)
        self.occupied = rasterize_segments(map_data.segments(), self.origin, cell_size, self.shape)
        _, idx = ndimage.distance_transform_edt(~self.occupied, return_indices=True)
        # idx[0] = row (iy), idx[1] = column (ix) of the nearest occupied cell.
        self.nearest_x = self.origin[0] + (idx[1] + 0.5) * cell_size
        self.nearest_y = self.origin[1] + (idx[0] + 0.5) * cell_size
        self._flat_x = self.nearest_x.ravel()
        self._flat_y = self.nearest_y.ravel()

    def nearest(self, pts: np.ndarray) -> np.ndarray:
        """Nearest occupied cell centres ``(n, 2)`` for map-frame points ``(n, 2)``.

        Points outside the grid are looked up at the closest border cell; their true distance
        to the returned centre is still computed honestly by the caller.
        """
        nx, ny = self.nearest_xy(pts[:, 0], pts[:, 1])
        return np.column_stack([nx, ny])

    def nearest_xy(self, qx: np.ndarray, qy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`nearest` on separate coordinate arrays; returns ``(x, y)`` arrays."""
        ny, nx = self.shape
        inv = 1.0 / self.cell_size
        ix = np.floor((qx - self.origin[0]) * inv)
        iy = np.floor((qy - self.origin[1]) * inv)
        np.clip(ix, 0, nx - 1, out=ix)
        np.clip(iy, 0, ny - 1, out=iy)
        flat = (iy * nx + ix).astype(np.intp)
        return self._flat_x[flat], self._flat_y[flat]


class ICPLocalizer:
    """Grid-based ICP tracking (the paper's "ICP" baseline). Needs a start pose.

    Implements :class:`service.core.types.Localizer`. Poses are ``[x m, y m, theta rad]`` in
    the map frame.
    """

    method = "icp"

    def __init__(
        self,
        map_data: MapData,
        initial_pose: np.ndarray | None,
        config: ICPConfig | None = None,
    ) -> None:
        if config is not None and not isinstance(config, ICPConfig):
            raise LocalizationError(f"icp config must be ICPConfig, got {type(config).__name__}")
        self.config = config or ICPConfig()
        if self.config.gate_final > self.config.gate_initial:
            raise LocalizationError("icp config: gate_final must not exceed gate_initial")
        self.map_data = map_data
        self._pose = check_pose(initial_pose, self.method)
        self.grid = DistanceGrid(map_data, self.config.cell_size, self.config.margin)
        self.motion = Motion(MotionConfig(use_odometry=self.config.use_odometry, extrapolate=False))

    @property
    def pose(self) -> np.ndarray | None:
        """Last estimate ``[x, y, theta]`` (map frame), a copy."""
        return self._pose.copy()

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Restart tracking from ``initial_pose``; ``None`` raises (no global localisation).
        ``odom``: odometry pose at ``initial_pose`` (the next increment starts from it)."""
        self._pose = check_pose(initial_pose, self.method)
        self.motion.reset(odom)

    def update(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None = None
    ) -> Estimate:
        """Register one scan (ranges m, NaN = no return; angles rad, robot frame)."""
        cfg = self.config
        odom_v = check_odom(odom)
        pts = scan_points(ranges, angles, cfg.range_max)
        pose = self.motion.predict(self._pose, odom_v).pose
        if len(pts) < cfg.min_points:
            self._pose = pose
            return Estimate(
                pose=pose.copy(),
                status="lost",
                score=0.0,
                extras={"points": float(len(pts)), "iterations": 0.0},
            )
        px = np.ascontiguousarray(pts[:, 0])
        py = np.ascontiguousarray(pts[:, 1])
        x, y, th = (float(v) for v in pose)
        gate = cfg.gate_initial
        iterations = 0
        for it in range(cfg.max_iterations):
            iterations = it + 1
            c, s = math.cos(th), math.sin(th)
            qx = c * px - s * py + x
            qy = s * px + c * py + y
            mx, my = self.grid.nearest_xy(qx, qy)
            d2 = (qx - mx) ** 2 + (qy - my) ** 2
            keep = d2 < gate * gate
            n_keep = int(np.count_nonzero(keep))
            if n_keep < cfg.min_points:
                break
            if cfg.trim_fraction < 1.0:
                n_trim = max(cfg.min_points, math.ceil(cfg.trim_fraction * n_keep))
                if n_trim < n_keep:
                    cut = np.partition(d2[keep], n_trim - 1)[n_trim - 1]
                    keep &= d2 <= cut
            # Closed-form rigid LSQ: pose.rigid_transform_2d inlined (no per-iteration checks).
            sx, sy, tx_, ty_ = px[keep], py[keep], mx[keep], my[keep]
            csx, csy, ctx, cty = sx.mean(), sy.mean(), tx_.mean(), ty_.mean()
            ax, ay, bx, by = sx - csx, sy - csy, tx_ - ctx, ty_ - cty
            new_th = math.atan2(
                numeric.dot(ax, by) - numeric.dot(ay, bx), numeric.dot(ax, bx) + numeric.dot(ay, by)
            )
            c, s = math.cos(new_th), math.sin(new_th)
            new_x = float(ctx - (c * csx - s * csy))
            new_y = float(cty - (s * csx + c * csy))
            dt = math.hypot(new_x - x, new_y - y)
            dr = abs(math.remainder(new_th - th, 2.0 * math.pi))
            x, y, th = new_x, new_y, new_th
            at_final_gate = gate <= cfg.gate_final
            gate = max(cfg.gate_final, gate * cfg.gate_decay)
            if at_final_gate and dt < cfg.tol_translation and dr < cfg.tol_rotation:
                break
        pose = np.array([x, y, wrap_angle(th)], dtype=np.float64)
        c, s = math.cos(th), math.sin(th)
        qx = c * px - s * py + x
        qy = s * px + c * py + y
        mx, my = self.grid.nearest_xy(qx, qy)
        d = np.hypot(qx - mx, qy - my)
        inl = d < cfg.gate_final
        inlier_fraction = float(inl.mean())
        rms = float(np.sqrt(np.mean(d[inl] ** 2))) if inl.any() else math.inf
        tracking = inlier_fraction >= cfg.tracking_min_inliers and rms <= cfg.tracking_max_rms
        quality = max(0.0, 1.0 - rms / cfg.gate_final) if inl.any() else 0.0
        self._pose = pose
        return Estimate(
            pose=pose.copy(),
            status="tracking" if tracking else "lost",
            score=float(np.clip(inlier_fraction * quality, 0.0, 1.0)),
            explained=inlier_fraction,
            extras={
                "points": float(len(pts)),
                "iterations": float(iterations),
                "inlier_fraction": inlier_fraction,
                "rms_m": rms if math.isfinite(rms) else -1.0,
            },
        )
