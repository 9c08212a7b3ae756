"""CARMEN logs (``.clf``, ``.log``, ``.txt``, plain or gzipped): ``FLASER``, ``ROBOTLASER1``,
``ODOM``, ``PARAM``; GMapping-corrected logs (``*.gfs.log``) alike.

Lines (whitespace separated; ``#`` starts a comment line; other message types are skipped)::

    FLASER n r1..rn x y theta odom_x odom_y odom_theta timestamp host logger_timestamp
    ROBOTLASER1 type start_angle fov resolution max_range accuracy remission_mode
                n r1..rn m e1..em laser_x laser_y laser_theta robot_x robot_y robot_theta
                tv rv forward_safety side_safety turn_axis timestamp host logger_timestamp
    ODOM x y theta tv rv accel timestamp host logger_timestamp
    PARAM name value timestamp host logger_timestamp

(``host logger_timestamp`` may be missing.) A scan's stamp is its ``timestamp`` field.

- ``FLASER`` beams: ``angle_min = -pi/2``, ``angle_increment = pi/(n-1)`` for every ``n``: the
  first and last beams point at -90 deg and +90 deg (180 beams: 1.006 deg steps; 361 beams:
  0.5 deg). The lines do not state it; GMapping's own tools step ``pi/180`` (180/181 beams) or
  ``pi/360`` (360/361) from -90 deg instead. Measured on the reference poses (scan pairs 1-6
  corrected scans apart that turned > 14 deg, mean trimmed nearest-neighbour gap) the two
  differ by less than 0.2 % (intel 0.06539 m vs 0.06527 m, fr079 0.05161 vs 0.05159 m), i.e. the
  data cannot tell; ``pi/(n-1)`` is what the ROS bags of the same runs state (intel 180 beams,
  increment 0.0175508 = pi/179; fr079 360 beams, 0.0087510 = pi/359), so a scan read from a
  CARMEN log and from the bag of the same run has the same beam angles.
- ``FLASER`` ranges: valid in ``(0, 80]`` m (the bags of these runs state ``range_max = 80``;
  the SICK no-return codes 81.83 / 81.91 m become NaN). ``ROBOTLASER1`` states its maximum; a
  reading at or above it is a no-return.
- Odometry of a raw log: ``FLASER``'s ``odom_x odom_y odom_theta`` (the robot's odometry at the
  scan), composed with ``PARAM robot_frontlaser_offset`` (metres forward; 0 when absent; only the
  PARAMs before the first laser line count); ``ROBOTLASER1``'s robot pose composed with the
  offset between its robot and laser poses (from the first such line). ``ODOM`` lines are
  validated but not interpolated: the laser lines carry the odometry at their own stamp.
- A GMapping-corrected log (detected by its ``NEFF`` lines; or ``corrected=True``): the laser
  line's ``x y theta`` (``ROBOTLASER1``: laser pose) is the corrected pose, returned as
  ``reference`` with ``reference_ok=True``, unchanged (the laser frame: see
  :mod:`service.adapters.logs`); such a log has no odometry (``odom=None``). Its stamps are relative
  and printed with 6 significant digits (mit-csail's are all ``1.13486e+09``): align such scans
  with other logs by order, never by stamp. Lines are yielded in file order: intel's corrected
  log has 4 adjacent pairs of laser lines in swapped stamp order (sort by ``stamp`` if needed).
"""

from __future__ import annotations

import gzip
import io
import math
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import numpy as np

from service.adapters.logs.scan import LogInfo, LogScan, clean_ranges
from service.core.pose import compose, relative
from service.errors import LogFormatError

#: Field of view of a FLASER line (rad): first beam at -pi/2, last at +pi/2.
FLASER_FOV = math.pi
#: Valid FLASER readings are at most this long (m).
CARMEN_RANGE_MAX = 80.0
LASER_MESSAGES = ("FLASER", "ROBOTLASER1")
#: The scan count is taken (one quick pass) only for files up to this size (bytes).
COUNT_LIMIT_BYTES = 64 * 2**20
#: How many lines the header pass reads at most looking for PARAMs, lasers and NEFF.
PRESCAN_LINES = 200_000


def open_text(path: Path) -> TextIO:
    """Open a plain or gzipped (by magic bytes) text file; latin-1 so that every byte decodes
    and a corrupt line is reported with its number by the parser."""
    with open(path, "rb") as fh:
        gz = fh.read(2) == b"\x1f\x8b"
    if gz:
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="latin-1")
    return open(path, encoding="latin-1")


@dataclass
class _Laser:
    stamp: float
    angle_min: float
    angle_increment: float
    ranges: np.ndarray
    range_max: float  # FLASER: CARMEN_RANGE_MAX; ROBOTLASER1: its stated maximum
    stated_max: bool  # True: a reading at range_max is a no-return
    pose: np.ndarray  # FLASER x y theta; ROBOTLASER1 laser pose
    odom: np.ndarray  # FLASER odom_x..; ROBOTLASER1 robot pose


def _floats(tokens: Sequence[str], where: str, what: str) -> list[float]:
    try:
        return [float(t) for t in tokens]
    except ValueError as exc:
        raise LogFormatError(f"{where}: {what}: not a number ({exc})") from None


def _finite(values: Sequence[float], where: str, what: str) -> None:
    if not all(math.isfinite(v) for v in values):
        raise LogFormatError(f"{where}: {what} is not finite: {list(values)}")


def _count(tok: str, where: str, what: str) -> int:
    try:
        n = int(tok)
    except ValueError:
        raise LogFormatError(f"{where}: {what}: count {tok!r} is not an integer") from None
    if n <= 0:
        raise LogFormatError(f"{where}: {what}: count {n} must be positive")
    return n


def parse_flaser(tokens: Sequence[str], where: str) -> _Laser:
    """Parse the tokens of one ``FLASER`` line; ``where`` is ``"file:line"`` for errors."""
    if len(tokens) < 2:
        raise LogFormatError(f"{where}: FLASER: no beam count")
    n = _count(tokens[1], where, "FLASER")
    if len(tokens) not in (n + 9, n + 11):
        raise LogFormatError(
            f"{where}: FLASER with {n} beams needs {n + 11} fields (or {n + 9} without host and "
            f"logger time), got {len(tokens)}"
        )
    ranges = np.array(_floats(tokens[2 : 2 + n], where, "FLASER ranges"))
    tail = _floats(tokens[2 + n : 2 + n + 7], where, "FLASER poses/timestamp")
    _finite(tail, where, "FLASER poses/timestamp")
    return _Laser(
        stamp=tail[6],
        angle_min=-0.5 * FLASER_FOV,
        angle_increment=FLASER_FOV / (n - 1) if n > 1 else 0.0,
        ranges=ranges,
        range_max=CARMEN_RANGE_MAX,
        stated_max=False,
        pose=np.array(tail[0:3]),
        odom=np.array(tail[3:6]),
    )


def parse_robotlaser1(tokens: Sequence[str], where: str) -> _Laser:
    """Parse the tokens of one ``ROBOTLASER1`` line; ``where`` is ``"file:line"`` for errors."""
    if len(tokens) < 10:
        raise LogFormatError(f"{where}: ROBOTLASER1: {len(tokens)} fields, too short")
    head = _floats(tokens[2:7], where, "ROBOTLASER1 start_angle/fov/resolution/max_range/accuracy")
    _finite(head, where, "ROBOTLASER1 start_angle/fov/resolution/max_range/accuracy")
    start, _fov, res, rmax, _acc = head
    if not rmax > 0.0:
        raise LogFormatError(f"{where}: ROBOTLASER1: maximum range {rmax} must be positive")
    n = _count(tokens[8], where, "ROBOTLASER1 num_readings")
    if len(tokens) < 10 + n:
        raise LogFormatError(f"{where}: ROBOTLASER1 with {n} readings: line too short")
    ranges = np.array(_floats(tokens[9 : 9 + n], where, "ROBOTLASER1 ranges"))
    try:
        m = int(tokens[9 + n])
    except ValueError:
        raise LogFormatError(
            f"{where}: ROBOTLASER1: remission count {tokens[9 + n]!r} is not an integer"
        ) from None
    if m < 0:
        raise LogFormatError(f"{where}: ROBOTLASER1: remission count {m} is negative")
    rest = 10 + n + m
    if len(tokens) not in (rest + 12, rest + 14):
        raise LogFormatError(
            f"{where}: ROBOTLASER1 with {n} readings and {m} remissions needs {rest + 14} fields "
            f"(or {rest + 12} without host and logger time), got {len(tokens)}"
        )
    _floats(tokens[10 + n : rest], where, "ROBOTLASER1 remissions")
    tail = _floats(tokens[rest : rest + 12], where, "ROBOTLASER1 poses/velocities/timestamp")
    _finite(tail, where, "ROBOTLASER1 poses/velocities/timestamp")
    return _Laser(
        stamp=tail[11],
        angle_min=start,
        angle_increment=res,
        ranges=ranges,
        range_max=rmax,
        stated_max=True,
        pose=np.array(tail[0:3]),
        odom=np.array(tail[3:6]),
    )


def check_odom(tokens: Sequence[str], where: str) -> None:
    """Validate one ``ODOM x y theta tv rv accel timestamp [host logger_timestamp]`` line."""
    if len(tokens) not in (8, 10):
        raise LogFormatError(f"{where}: ODOM needs 10 fields (or 8), got {len(tokens)}")
    vals = _floats(tokens[1:8], where, "ODOM")
    _finite(vals, where, "ODOM")


def _param(tokens: Sequence[str], where: str) -> tuple[str, str]:
    if len(tokens) < 3:
        raise LogFormatError(f"{where}: PARAM needs a name and a value, got {len(tokens)} fields")
    return tokens[1], tokens[2]


@dataclass
class _Header:
    params: dict[str, str] = field(default_factory=dict)
    first: _Laser | None = None
    first_kind: str | None = None
    corrected: bool = False


def _prescan(path: Path) -> _Header:
    """PARAMs before the first laser line, the first laser line, and whether ``NEFF`` lines
    (GMapping's effective particle count) come before the third laser line."""
    head = _Header()
    lasers = 0
    with open_text(path) as fh:
        for lineno, line in enumerate(fh, 1):
            if lineno > PRESCAN_LINES or lasers >= 3:
                break
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            kw = tokens[0]
            where = f"{path}:{lineno}"
            if kw == "PARAM" and lasers == 0:
                try:
                    name, value = _param(tokens, where)
                except LogFormatError:
                    continue  # reported (or skipped) by the streaming pass
                head.params[name] = value
            elif kw == "NEFF":
                head.corrected = True
                break
            elif kw in LASER_MESSAGES:
                lasers += 1
                if head.first is None:
                    try:
                        head.first = (
                            parse_flaser(tokens, where)
                            if kw == "FLASER"
                            else parse_robotlaser1(tokens, where)
                        )
                        head.first_kind = kw
                    except LogFormatError:
                        lasers -= 1
    return head


def _count_scans(path: Path) -> int | None:
    if path.stat().st_size > COUNT_LIMIT_BYTES:
        return None
    with open(path, "rb") as fh:
        gz = fh.read(2) == b"\x1f\x8b"
    opener = gzip.open if gz else open
    count = 0
    with opener(path, "rb") as fh:
        for line in fh:
            if line.startswith((b"FLASER ", b"ROBOTLASER1 ")):
                count += 1
    return count


def read_carmen(
    path: Path,
    *,
    max_range: float | None = None,
    limit: int | None = None,
    laser_offset: Sequence[float] | None = None,
    skip_bad_lines: bool = False,
    corrected: bool | None = None,
) -> tuple[LogInfo, Iterator[LogScan]]:
    """Open a CARMEN log; see :func:`service.adapters.logs.read_log` and this module's docstring."""
    head = _prescan(path)
    is_corrected = head.corrected if corrected is None else bool(corrected)
    if laser_offset is not None:
        offset = np.asarray(laser_offset, dtype=np.float64).reshape(3)
        source = "given"
    elif head.first_kind == "ROBOTLASER1" and head.first is not None:
        offset = relative(head.first.odom, head.first.pose)
        source = "ROBOTLASER1"
    elif "robot_frontlaser_offset" in head.params:
        value = head.params["robot_frontlaser_offset"]
        try:
            offset = np.array([float(value), 0.0, 0.0])
        except ValueError:
            raise LogFormatError(
                f"{path}: PARAM robot_frontlaser_offset {value!r} is not a number"
            ) from None
        source = "PARAM robot_frontlaser_offset"
    else:
        offset, source = np.zeros(3), "none"
    first = head.first
    info = LogInfo(
        format="carmen",
        path=path,
        scan_count=_count_scans(path),
        beams=int(first.ranges.shape[0]) if first is not None else None,
        angle_min=first.angle_min if first is not None else None,
        angle_increment=first.angle_increment if first is not None else None,
        laser_offset=offset,
        laser_offset_source=source,
        scan_topic=head.first_kind,
        odom_topic=None if is_corrected or first is None else head.first_kind,
        corrected=is_corrected,
    )
    return info, _stream(info, max_range, limit, skip_bad_lines)


def _stream(
    info: LogInfo, max_range: float | None, limit: int | None, skip_bad_lines: bool
) -> Iterator[LogScan]:
    if limit is not None and limit <= 0:
        return
    path = info.path
    index = 0
    with open_text(path) as fh:
        for lineno, line in enumerate(fh, 1):
            tokens = line.split()
            if not tokens or tokens[0].startswith("#"):
                continue
            kw = tokens[0]
            where = f"{path}:{lineno}"
            try:
                if kw == "FLASER":
                    laser = parse_flaser(tokens, where)
                elif kw == "ROBOTLASER1":
                    laser = parse_robotlaser1(tokens, where)
                else:
                    if kw == "ODOM":
                        check_odom(tokens, where)
                    elif kw == "PARAM":
                        _param(tokens, where)
                    continue
            except LogFormatError as exc:
                if not skip_bad_lines:
                    raise
                info.bad_lines.append(str(exc))
                continue
            yield _scan(info, index, laser, max_range)
            index += 1
            if limit is not None and index >= limit:
                return


def _scan(info: LogInfo, index: int, laser: _Laser, max_range: float | None) -> LogScan:
    rmax, include_max = laser.range_max, not laser.stated_max
    if max_range is not None and max_range < rmax:
        rmax, include_max = float(max_range), True
    odom = reference = None
    if info.corrected:
        reference = laser.pose
    else:
        odom = compose(laser.odom, info.laser_offset)
    return LogScan(
        index=index,
        stamp=laser.stamp,
        angle_min=laser.angle_min,
        angle_increment=laser.angle_increment,
        range_min=0.0,
        range_max=rmax,
        ranges=clean_ranges(laser.ranges, 0.0, rmax, include_max=include_max),
        odom=odom,
        reference=reference,
        reference_ok=reference is not None,
    )
