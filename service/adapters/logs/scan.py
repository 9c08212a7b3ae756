"""What every log reader yields: :class:`LogScan` records, a :class:`LogInfo` summary, and the
helpers they share (range cleaning, odometry interpolation at a scan's stamp).

Units: metres, radians, seconds. Poses are ``[x, y, theta]`` float64 arrays (REP 103: the pose
of a frame in its parent frame, theta counter-clockwise, as in :mod:`service.core.pose`).
"""

from __future__ import annotations

import bisect
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from service.core.types import wrap_angle
from service.errors import LogFormatError

#: A scan stamp outside the odometry's time span still gets the nearest odometry pose when it is
#: at most this far (s) from it (fr079's first scan precedes its first odometry message by 10 ms,
#: intel's last scan follows its last one by 9 ms); farther away the scan gets ``odom = None``.
ODOM_HOLD_S = 0.5


def _frozen(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


@dataclass(frozen=True, eq=False)
class LogScan:
    """One laser scan of a log, in the LASER frame.

    - ``index``: 0-based position of the scan in the log (every scan counts, also one whose
      odometry is missing).
    - ``stamp``: seconds on the log's own clock. ROS bags: the scan's ``header.stamp`` as stored
      (``sec + nanosec * 1e-9``), the clock of the Kümmerle relations and of the
      ``*.gfs_reference_per_scan.txt`` files. CARMEN: the message's ``timestamp`` field (the
      field after the poses; not the logger's time at the end of the line).
    - ``angle_min``, ``angle_increment`` (rad): beam ``i`` points at
      ``angle_min + i * angle_increment`` in the laser frame (x forward, y left).
    - ``range_min``, ``range_max`` (m): the valid interval used to clean ``ranges``.
    - ``ranges``: ``(n,)`` float64 metres, read-only; ``NaN`` for every no-return: NaN, inf,
      ``<= 0``, outside ``[range_min, range_max]`` (the SICK "max range" codes 81.83 / 81.91 m
      fall outside every reader's ``range_max``).
    - ``odom``: ``(3,)`` odometry pose of the LASER frame at ``stamp`` (the log's odometry composed
      with the laser offset, interpolated between odometry messages, theta on the circle), or
      ``None`` when the log has no odometry at that time. Only increments of it are meaningful.
    - ``reference``: ``(3,)`` reference pose of the laser frame in the reference's map frame, or
      ``None``; ``reference_ok``: whether it is trustworthy (flag 1 of a
      ``gfs_reference_per_scan`` file, or a corrected pose of a GMapping-corrected log).
    """

    index: int
    stamp: float
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: np.ndarray
    odom: np.ndarray | None = None
    reference: np.ndarray | None = None
    reference_ok: bool = False

    @property
    def beams(self) -> int:
        """Number of beams ``n``."""
        return int(self.ranges.shape[0])

    @property
    def angles(self) -> np.ndarray:
        """``(n,)`` beam angles (rad) in the laser frame."""
        return self.angle_min + self.angle_increment * np.arange(self.beams, dtype=np.float64)

    def points(self) -> np.ndarray:
        """``(k, 2)`` end points (m) of the valid beams in the laser frame."""
        ok = np.isfinite(self.ranges)
        a = self.angles[ok]
        r = self.ranges[ok]
        return np.column_stack([r * np.cos(a), r * np.sin(a)])


@dataclass(frozen=True)
class LogInfo:
    """What a reader found out about a log before streaming its scans.

    - ``format``: ``"ros1"``, ``"ros2"`` or ``"carmen"``; ``path``: the file or bag directory.
    - ``scan_count``: scans in the whole log (``limit`` not applied), ``None`` when not cheap to
      know (a CARMEN log above 64 MB).
    - ``beams``, ``angle_min``, ``angle_increment`` (rad), ``fov`` (rad, first to last beam):
      of the first scan (``None`` for a log without scans).
    - ``laser_offset``: ``(3,)`` pose of the laser in the robot base frame that the reader composed
      with the odometry; ``laser_offset_source`` says where it came from (``"tf_static"``,
      ``"PARAM robot_frontlaser_offset"``, ``"ROBOTLASER1"``, ``"given"`` or ``"none"``).
    - ``scan_topic`` / ``odom_topic``: the bag topics read (``odom_topic`` is ``"/tf"`` for
      odom->base transforms), or for CARMEN the message names (``"FLASER"``, ...).
    - ``odom_frames``: ``(parent, child)`` frames of the odometry; ``laser_frame``: the scan's.
    - ``corrected``: a GMapping-corrected CARMEN log (``NEFF`` lines): the laser lines' pose is
      the corrected pose, returned as ``reference``, and there is no odometry.
    - ``duration``: seconds from first to last message when cheap (bags), else ``None``.
    - ``bad_lines``: filled while iterating with ``skip_bad_lines=True``: one ``"file:line:
      problem"`` string per skipped line.
    """

    format: str
    path: Path
    scan_count: int | None
    beams: int | None
    angle_min: float | None
    angle_increment: float | None
    laser_offset: np.ndarray
    laser_offset_source: str
    scan_topic: str | None
    odom_topic: str | None
    odom_frames: tuple[str, str] | None = None
    laser_frame: str | None = None
    corrected: bool = False
    duration: float | None = None
    bad_lines: list[str] = field(default_factory=list)

    @property
    def fov(self) -> float | None:
        """Angle (rad) from the first to the last beam, ``None`` without scans."""
        if self.beams is None or self.angle_increment is None:
            return None
        return self.angle_increment * (self.beams - 1)

    @property
    def has_odom(self) -> bool:
        """Whether the reader found an odometry source."""
        return self.odom_topic is not None


def clean_ranges(
    raw: np.ndarray,
    range_min: float,
    range_max: float,
    *,
    include_max: bool = True,
) -> np.ndarray:
    """``(n,)`` float64 copy of ``raw`` (m) with ``NaN`` for no-returns (read-only).

    A reading is kept when it is finite, ``> 0`` and inside ``[range_min, range_max]``
    (``[range_min, range_max)`` with ``include_max=False``: CARMEN reports a no-return as its
    stated maximum range).
    """
    r = np.array(raw, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(r) | (r <= 0.0) | (r < range_min)
        bad |= (r > range_max) if include_max else (r >= range_max)
    r[bad] = np.nan
    return _frozen(r)


class OdometryTrack:
    """Odometry poses ``[x, y, theta]`` of one frame, kept sorted by stamp, interpolated on demand.

    Poses are appended as they are read (out-of-order stamps are inserted in place); equal stamps
    keep the later pose. :meth:`at` interpolates x and y linearly and theta along the shorter arc.
    """

    def __init__(self) -> None:
        self._t: list[float] = []
        self._p: list[tuple[float, float, float]] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def last_stamp(self) -> float:
        """Latest stamp held (s); ``-inf`` when empty."""
        return self._t[-1] if self._t else -math.inf

    def add(self, stamp: float, x: float, y: float, theta: float) -> None:
        """Add the pose at ``stamp`` (s)."""
        p = (float(x), float(y), float(theta))
        if not self._t or stamp > self._t[-1]:
            self._t.append(stamp)
            self._p.append(p)
            return
        k = bisect.bisect_left(self._t, stamp)
        if k < len(self._t) and self._t[k] == stamp:
            self._p[k] = p
        else:
            self._t.insert(k, stamp)
            self._p.insert(k, p)

    def at(self, stamp: float, hold: float = ODOM_HOLD_S) -> np.ndarray | None:
        """``(3,)`` pose at ``stamp`` (s), or ``None`` when it lies more than ``hold`` seconds
        outside the track (the nearest end pose is returned within ``hold``)."""
        t = self._t
        if not t:
            return None
        if stamp <= t[0]:
            return np.array(self._p[0]) if t[0] - stamp <= hold else None
        if stamp >= t[-1]:
            return np.array(self._p[-1]) if stamp - t[-1] <= hold else None
        k = bisect.bisect_right(t, stamp)  # t[k-1] <= stamp < t[k]
        t0, t1 = t[k - 1], t[k]
        p0, p1 = self._p[k - 1], self._p[k]
        w = (stamp - t0) / (t1 - t0)
        dth = float(wrap_angle(p1[2] - p0[2]))
        return np.array(
            [
                p0[0] + w * (p1[0] - p0[0]),
                p0[1] + w * (p1[1] - p0[1]),
                float(wrap_angle(p0[2] + w * dth)),
            ]
        )


def yaw_of_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Yaw (rad) of a quaternion (rotation about z of the ZYX Euler decomposition)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def tilt_of_quaternion(x: float, y: float, z: float, w: float) -> float:
    """Angle (rad) between the rotated z axis and the z axis: 0 for a level (yaw-only) mount."""
    zz = 1.0 - 2.0 * (x * x + y * y)
    return math.acos(max(-1.0, min(1.0, zz)))


def numbered_lines(path: Path) -> Iterator[tuple[int, str]]:
    """``(line number from 1, line)`` of a text file (latin-1, so that every byte decodes);
    an unreadable file raises :class:`LogFormatError` naming it."""
    try:
        fh = open(path, encoding="latin-1")  # noqa: SIM115 - closed below, error names the file
    except OSError as exc:
        raise LogFormatError(f"{path}: cannot read: {exc}") from exc
    with fh:
        yield from enumerate(fh, 1)
