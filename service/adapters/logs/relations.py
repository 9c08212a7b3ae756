"""Kümmerle relations (``*.relations``) and the relations metric (Kümmerle et al. 2009, "On
measuring the accuracy of SLAM algorithms").

File format, one relation a line::

    t1 t2 x y z roll pitch yaw

the pose at stamp ``t2`` expressed in the robot frame at stamp ``t1`` (m, rad; ``z``, ``roll``,
``pitch`` are zero for these 2D logs and ignored).

Metric: for every relation, ``delta_hat = x(t1)^-1 (+) x(t2)`` from the estimated poses and
``e = delta* (-) delta_hat`` (``delta_hat`` in the frame of ``delta*``); the translational error
is ``|e.xy|`` (m), the rotational error ``|wrap(e.theta)|`` (reported in degrees). Mean,
population standard deviation and maximum over the relations whose two stamps both have a
(valid) estimate; the others are counted as skipped.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.adapters.logs.reference import match_stamps
from service.adapters.logs.scan import numbered_lines
from service.core.pose import compose, relative
from service.core.types import wrap_angle
from service.errors import LogFormatError

#: Smallest stamp tolerance (s) used when matching relation stamps to estimates.
MIN_TOLERANCE = 1e-6


@dataclass(frozen=True, eq=False)
class Relations:
    """``t1``, ``t2`` ``(m,)`` stamps (s); ``delta`` ``(m, 3)`` ``[x, y, yaw]`` of the pose at
    ``t2`` in the frame at ``t1``; ``tolerance`` (s): how far an estimate's stamp may be from a
    relation's (one unit of the last decimal the file prints, at least 1e-6: mit-csail's
    relations round its 6-decimal stamps to 5 decimals)."""

    t1: np.ndarray
    t2: np.ndarray
    delta: np.ndarray
    tolerance: float = MIN_TOLERANCE
    path: Path | None = None

    def __len__(self) -> int:
        return int(self.t1.shape[0])


def _decimals(token: str) -> int:
    mantissa = token.lower().split("e")[0]
    return len(mantissa.split(".")[1]) if "." in mantissa else 0


def load_relations(path: str | Path) -> Relations:
    """Read a relations file (module docstring); malformed lines raise :class:`LogFormatError`."""
    path = Path(path)
    rows: list[list[float]] = []
    decimals = 9
    for lineno, line in numbered_lines(path):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        where = f"{path}:{lineno}"
        if len(tokens) != 8:
            raise LogFormatError(
                f"{where}: expected 't1 t2 x y z roll pitch yaw', got {len(tokens)} fields"
            )
        try:
            vals = [float(v) for v in tokens]
        except ValueError:
            raise LogFormatError(f"{where}: not a number in {line.strip()!r}") from None
        if not all(math.isfinite(v) for v in vals):
            raise LogFormatError(f"{where}: non-finite value in {line.strip()!r}")
        decimals = min(decimals, _decimals(tokens[0]), _decimals(tokens[1]))
        rows.append(vals)
    a = np.array(rows, dtype=np.float64).reshape(-1, 8)
    return Relations(
        t1=a[:, 0].copy(),
        t2=a[:, 1].copy(),
        delta=a[:, [2, 3, 7]].copy(),
        tolerance=max(MIN_TOLERANCE, 10.0**-decimals),
        path=path,
    )


@dataclass(frozen=True, eq=False)
class RelationsError:
    """Result of :func:`relations_error`: translation (m) and rotation (deg) error statistics
    over ``used`` relations (NaN when none), ``skipped`` relations without two (valid) estimates,
    and the per-relation errors ``translation`` (m) and ``rotation`` (deg) of the used ones."""

    translation_mean: float
    translation_std: float
    translation_max: float
    rotation_mean: float
    rotation_std: float
    rotation_max: float
    used: int
    skipped: int
    translation: np.ndarray
    rotation: np.ndarray

    def __str__(self) -> str:
        return (
            f"{self.translation_mean:.4f} ± {self.translation_std:.4f} m (max "
            f"{self.translation_max:.3f}), {self.rotation_mean:.3f} ± {self.rotation_std:.3f} deg"
            f" (max {self.rotation_max:.2f}); {self.used} relations, {self.skipped} skipped"
        )


def relations_error(
    stamps: Sequence[float] | np.ndarray,
    poses: Sequence[Sequence[float]] | np.ndarray,
    relations: Relations,
    valid: Sequence[bool] | np.ndarray | None = None,
    *,
    tolerance: float | None = None,
    frame_offset: Sequence[float] | None = None,
) -> RelationsError:
    """Score estimated ``poses`` ``(n, 3)`` at ``stamps`` ``(n,)`` (s) against ``relations``.

    ``valid`` ``(n,)``: estimates to use (default all); estimates with a non-finite value are never
    used. A relation stamp matches the nearest estimate stamp within ``tolerance`` s (default
    ``relations.tolerance``). ``frame_offset``: pose of the relations' robot frame in the frame of
    ``poses``; each pose is composed with it first (default: the same frame; see
    :mod:`service.adapters.logs` for what an offset does to fr079's figure).
    """
    t = np.asarray(stamps, dtype=np.float64).reshape(-1)
    p = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    if p.shape[0] != t.shape[0]:
        raise LogFormatError(f"relations_error: {t.shape[0]} stamps but {p.shape[0]} poses")
    use = np.all(np.isfinite(p), axis=1) & np.isfinite(t)
    if valid is not None:
        v = np.asarray(valid, dtype=bool).reshape(-1)
        if v.shape[0] != t.shape[0]:
            raise LogFormatError(f"relations_error: {t.shape[0]} stamps but {v.shape[0]} flags")
        use &= v
    keep = np.flatnonzero(use)
    t, p = t[keep], p[keep]
    if frame_offset is not None:
        off = np.asarray(frame_offset, dtype=np.float64).reshape(3)
        p = np.array([compose(q, off) for q in p]).reshape(-1, 3)
    tol = relations.tolerance if tolerance is None else float(tolerance)
    i1 = match_stamps(t, relations.t1, tol)
    i2 = match_stamps(t, relations.t2, tol)
    hit = (i1 >= 0) & (i2 >= 0)
    et: list[float] = []
    er: list[float] = []
    for a, b, d in zip(i1[hit], i2[hit], relations.delta[hit], strict=True):
        e = relative(d, relative(p[a], p[b]))
        et.append(math.hypot(e[0], e[1]))
        er.append(abs(float(wrap_angle(e[2]))))
    trans = np.array(et, dtype=np.float64)
    rot = np.degrees(np.array(er, dtype=np.float64))

    def stats(x: np.ndarray) -> tuple[float, float, float]:
        if x.size == 0:
            return math.nan, math.nan, math.nan
        return float(x.mean()), float(x.std()), float(x.max())

    tm, ts, tx = stats(trans)
    rm, rs, rx = stats(rot)
    return RelationsError(
        translation_mean=tm,
        translation_std=ts,
        translation_max=tx,
        rotation_mean=rm,
        rotation_std=rs,
        rotation_max=rx,
        used=int(hit.sum()),
        skipped=int((~hit).sum()),
        translation=trans,
        rotation=rot,
    )
