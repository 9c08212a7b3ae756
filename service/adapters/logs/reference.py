"""Per-scan reference poses (``*.gfs_reference_per_scan.txt``) and their alignment with scans.

File format: ``#`` comment lines, then one line per raw scan in log order::

    raw_stamp x y theta flag

``raw_stamp`` is the raw scan's stamp (s, 6 decimals; equal to the bag's ``header.stamp`` and to
the relations' stamps), ``x y theta`` the GMapping-corrected pose (m, rad; map frame with the first
pose at the origin) and ``flag`` 1 for a pose GMapping corrected, 0 for one carried forward by
odometry (not a reference: do not score against it).

Frame: the poses are of the LASER frame, used as given. Measured on fr079, whose laser is 4 cm
off the base: drawing each scan at its reference pose composed with a shift ``L`` along the
heading and comparing scan pairs 1-6 corrected scans apart that turned > 14 deg (mean trimmed
nearest-neighbour gap, 3 020 pairs) gives 0.05476 m at L = -0.04, 0.05283 m at L = 0 and
0.05453 m at L = +0.04 (intel: 0.03771 / 0.03315 / 0.03506), and the bag's odometry increments
match the reference increments best unshifted (median gap 0.0420 m at 0 vs 0.0467 m at -0.04,
0.0488 m at +0.04; 8 760 pairs). See :mod:`service.adapters.logs` for the relations' frame.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from service.adapters.logs.scan import LogScan, numbered_lines
from service.core.pose import compose
from service.errors import LogFormatError

#: Default stamp tolerance (s) when matching scans to reference stamps.
STAMP_TOLERANCE = 1e-6


@dataclass(frozen=True, eq=False)
class ReferenceTrack:
    """Reference poses, one per raw scan, in log order.

    ``stamps`` ``(n,)`` s; ``poses`` ``(n, 3)`` ``[x, y, theta]`` of the laser frame (m, rad);
    ``ok`` ``(n,)`` bool, True for a trustworthy (flag 1) pose; ``path`` the file read, if any.
    """

    stamps: np.ndarray
    poses: np.ndarray
    ok: np.ndarray
    path: Path | None = None

    def __post_init__(self) -> None:
        n = self.stamps.shape[0]
        if self.stamps.shape != (n,) or self.poses.shape != (n, 3) or self.ok.shape != (n,):
            raise LogFormatError(
                f"{self.path or 'reference'}: shapes differ: stamps {self.stamps.shape}, poses "
                f"{self.poses.shape}, ok {self.ok.shape}"
            )

    def __len__(self) -> int:
        return int(self.stamps.shape[0])

    def find(self, stamps: np.ndarray, tolerance: float = STAMP_TOLERANCE) -> np.ndarray:
        """Row of the nearest reference stamp within ``tolerance`` s for each of ``stamps``;
        -1 where there is none."""
        return match_stamps(self.stamps, np.asarray(stamps, dtype=np.float64), tolerance)


def match_stamps(known: np.ndarray, query: np.ndarray, tolerance: float) -> np.ndarray:
    """For each ``query`` stamp, the index into ``known`` of the nearest stamp within
    ``tolerance`` (s), or -1. ``known`` need not be sorted."""
    out = np.full(query.shape, -1, dtype=np.int64)
    if known.size == 0 or query.size == 0:
        return out
    order = np.argsort(known, kind="stable")
    s = known[order]
    k = np.searchsorted(s, query)
    lo = np.clip(k - 1, 0, s.size - 1)
    hi = np.clip(k, 0, s.size - 1)
    d_lo = np.abs(query - s[lo])
    d_hi = np.abs(s[hi] - query)
    best = np.where(d_hi < d_lo, hi, lo)
    d = np.minimum(d_lo, d_hi)
    hit = d <= tolerance
    out[hit] = order[best[hit]]
    return out


def load_reference(path: str | Path) -> ReferenceTrack:
    """Read a ``raw_stamp x y theta flag`` file (see the module docstring)."""
    path = Path(path)
    stamps: list[float] = []
    poses: list[tuple[float, float, float]] = []
    ok: list[bool] = []
    for lineno, line in numbered_lines(path):
        tokens = line.split()
        if not tokens or tokens[0].startswith("#"):
            continue
        where = f"{path}:{lineno}"
        if len(tokens) != 5:
            raise LogFormatError(f"{where}: expected 'stamp x y theta flag', got {line.strip()!r}")
        try:
            t, x, y, th = (float(v) for v in tokens[:4])
            flag = int(tokens[4])
        except ValueError:
            raise LogFormatError(f"{where}: not a number in {line.strip()!r}") from None
        if not all(np.isfinite([t, x, y, th])) or flag not in (0, 1):
            raise LogFormatError(f"{where}: non-finite value or flag not 0/1: {line.strip()!r}")
        stamps.append(t)
        poses.append((x, y, th))
        ok.append(flag == 1)
    return ReferenceTrack(
        stamps=np.array(stamps, dtype=np.float64),
        poses=np.array(poses, dtype=np.float64).reshape(-1, 3),
        ok=np.array(ok, dtype=bool),
        path=path,
    )


def attach_reference(
    scans: Iterable[LogScan],
    track: ReferenceTrack,
    *,
    align: Literal["auto", "stamp", "order"] = "auto",
    scan_count: int | None = None,
    tolerance: float = STAMP_TOLERANCE,
    frame_offset: Sequence[float] | None = None,
) -> Iterator[LogScan]:
    """Yield ``scans`` with ``reference`` / ``reference_ok`` filled from ``track`` (lazily).

    - ``align="stamp"``: the row whose stamp is within ``tolerance`` s of the scan's; a scan
      without one gets ``reference=None``.
    - ``align="order"``: row ``scan.index`` (the track lists every raw scan in log order); an
      index beyond the track raises :class:`LogFormatError`.
    - ``align="auto"``: by stamp when the first scan's stamp is in the track; otherwise by order,
      allowed only when ``scan_count`` (the log's scan count, e.g. ``LogInfo.scan_count``) is
      unknown or equals ``len(track)``.

    ``frame_offset``: pose of the laser in the frame the track's poses describe; the poses are
    composed with it. ``None`` (default) keeps them as they are: the GMapping references are
    already laser poses (module docstring).
    """
    offset = None if frame_offset is None else np.asarray(frame_offset, dtype=np.float64)
    where = track.path or "reference"
    mode = align
    for scan in scans:
        if mode == "auto":
            if track.find(np.array([scan.stamp]), tolerance)[0] >= 0:
                mode = "stamp"
            elif scan_count is None or scan_count == len(track):
                mode = "order"
            else:
                raise LogFormatError(
                    f"{where}: scan stamp {scan.stamp:.6f} is not in the reference and the log has "
                    f"{scan_count} scans but the reference {len(track)}: cannot align"
                )
        if mode == "stamp":
            row = int(track.find(np.array([scan.stamp]), tolerance)[0])
        elif mode == "order":
            row = scan.index
            if row >= len(track):
                raise LogFormatError(
                    f"{where}: scan index {row} beyond the reference's {len(track)} rows"
                )
        else:
            raise LogFormatError(f"unknown align {align!r} (auto, stamp, order)")
        if row < 0:
            yield dataclasses.replace(scan, reference=None, reference_ok=False)
            continue
        pose = track.poses[row].copy()
        if offset is not None:
            pose = compose(pose, offset)
        yield dataclasses.replace(scan, reference=pose, reference_ok=bool(track.ok[row]))
