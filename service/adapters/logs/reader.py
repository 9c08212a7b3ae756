"""One entry point for every log format: :func:`read_log` (and :func:`log_format`).

Formats by path: ROS 1 bag (``.bag``), ROS 2 bag (a directory with ``metadata.yaml``, or its
``.db3`` / ``.mcap`` file) -> :mod:`service.adapters.logs.bags`; CARMEN (``.clf``, ``.log``,
``.txt``,
each optionally ``.gz``) -> :mod:`service.adapters.logs.carmen`. Whatever the format, the scans
come as
:class:`~service.adapters.logs.scan.LogScan` (metres, radians, seconds on the log's clock) with
their odometry in the LASER frame (see :mod:`service.adapters.logs`); malformed input raises
:class:`~service.errors.LogFormatError` naming the file (and line or topic).
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path

from service.adapters.logs.bags import is_ros2_bag, read_bag
from service.adapters.logs.carmen import read_carmen
from service.adapters.logs.scan import LogInfo, LogScan
from service.errors import LogFormatError

#: File name endings read as CARMEN logs (each also with ``.gz``).
CARMEN_SUFFIXES = (".clf", ".log", ".txt")


def log_format(path: str | Path) -> str:
    """``"ros1"``, ``"ros2"`` or ``"carmen"`` from the path (see :func:`read_log`)."""
    p = Path(path)
    if not p.exists():
        raise LogFormatError(f"{p}: no such file or directory")
    if p.is_dir():
        if is_ros2_bag(p):
            return "ros2"
        raise LogFormatError(f"{p}: a directory without metadata.yaml is not a ROS 2 bag")
    if p.suffix == ".bag":
        return "ros1"
    if is_ros2_bag(p):
        return "ros2"
    name = p.name[: -len(".gz")] if p.name.endswith(".gz") else p.name
    if name.endswith(CARMEN_SUFFIXES):
        return "carmen"
    raise LogFormatError(
        f"{p}: unknown log format (ROS 1 .bag; ROS 2 bag directory, .db3 or .mcap; CARMEN "
        f"{', '.join(CARMEN_SUFFIXES)}, plain or .gz)"
    )


def read_log(
    path: str | Path,
    *,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    max_range: float | None = None,
    limit: int | None = None,
    laser_offset: Sequence[float] | None = None,
    skip_bad_lines: bool = False,
    corrected: bool | None = None,
) -> tuple[LogInfo, Iterator[LogScan]]:
    """Open a laser log; return its :class:`LogInfo` and a lazy iterator over its scans.

    The format follows the path (:func:`log_format`): ``.bag`` ROS 1; a directory holding
    ``metadata.yaml``, or a ``.db3`` / ``.mcap`` file, ROS 2; ``.clf`` / ``.log`` / ``.txt``
    (each optionally ``.gz``) CARMEN. The file is opened (and its header checked) now; scans are
    read as the iterator is consumed, and it closes the file when exhausted or closed.

    - ``scan_topic`` / ``odom_topic`` (bags only): default by message type (:mod:`.bags`);
      ``odom_topic="/tf"`` uses the ``odom -> base`` transforms.
    - ``max_range`` (m): readings beyond it become NaN too (``LogScan.range_max`` is capped).
    - ``limit``: stop after this many scans.
    - ``laser_offset``: ``[x, y, theta]`` pose of the laser in the base frame to compose the
      odometry with, instead of the one the log states (``/tf_static``, ``PARAM
      robot_frontlaser_offset``, ``ROBOTLASER1``); ``(0, 0, 0)`` uses the odometry as it is.
    - ``skip_bad_lines`` (CARMEN only): skip a malformed line and note it in
      ``LogInfo.bad_lines`` instead of raising :class:`LogFormatError`.
    - ``corrected`` (CARMEN only): force (True) or deny (False) the GMapping-corrected reading
      (laser poses as references, no odometry); default: detected from ``NEFF`` lines.
    """
    p = Path(path)
    fmt = log_format(p)
    if fmt == "carmen":
        if scan_topic is not None or odom_topic is not None:
            raise LogFormatError(f"{p}: a CARMEN log has no topics (scan_topic/odom_topic)")
        return read_carmen(
            p,
            max_range=max_range,
            limit=limit,
            laser_offset=laser_offset,
            skip_bad_lines=skip_bad_lines,
            corrected=corrected,
        )
    if corrected:
        raise LogFormatError(f"{p}: corrected=True applies to CARMEN logs only")
    return read_bag(
        p,
        scan_topic=scan_topic,
        odom_topic=odom_topic,
        max_range=max_range,
        limit=limit,
        laser_offset=laser_offset,
    )
