"""Recorded 2D laser logs: readers, per-scan reference poses and the relations metric.

Pure functions over files (no zenoh, no wire messages), used alike by the simulator's replay
(``shapeloc-sim replay``), the CLI and the benchmarks.

- :func:`read_log` opens a ROS 1 bag (``.bag``), a ROS 2 bag (directory with
  ``metadata.yaml``, ``.db3`` or ``.mcap``; both through ``rosbags``, no ROS install) or a CARMEN
  log (``.clf`` / ``.log`` / ``.txt``, plain or gzipped; ``FLASER``, ``ROBOTLASER1``, ``ODOM``,
  ``PARAM``; GMapping-corrected logs too) and returns a :class:`LogInfo` and a lazy iterator of
  :class:`LogScan`. Malformed input raises :class:`service.errors.LogFormatError` naming the
  file and the line (CARMEN) or topic (bags).
- :func:`load_reference` / :func:`attach_reference`: the ``raw_stamp x y theta flag`` per-scan
  reference files; each raw scan gets its row by exact stamp (or by order).
- :func:`load_relations` / :func:`relations_error`: Kümmerle et al.'s relations and metric.

Units: metres, radians, seconds (stamps on the log's own clock). Poses are ``[x, y, theta]``.

Frames. Every pose this package returns is of the LASER frame:

- ``LogScan.odom`` is the log's odometry of the robot base interpolated at the scan's stamp and
  composed with the laser's mounting offset (``LogInfo.laser_offset``: ``/tf_static`` in bags,
  ``PARAM robot_frontlaser_offset`` or ``ROBOTLASER1`` in CARMEN logs). So odometry and scan
  describe the same point, which is what a localiser that estimates the laser's pose needs;
  only its increments are meaningful (its origin is the odometry's).
- The GMapping references (``*.gfs_reference_per_scan.txt`` and the corrected logs' laser
  lines) are laser poses in GMapping's map frame and are used as given. Measured with
  :mod:`service.adapters.maps.build` / :mod:`service.adapters.maps.fidelity`: a map built from the
  flag-1 scans
  of fr079 (first 1 500 scans; laser 0.04 m ahead of ``base_link``) at the reference poses
  shifted by ``L`` along the heading puts those scans a median 0.0203 / 0.0179 / 0.0196 m from
  its polylines for ``L = -0.04 / 0 / +0.04`` m (intel, laser on the base: 0.0209 / 0.0158 /
  0.0187 m): the unshifted reference is the laser's pose, not the base's.
- The relations are scored on the poses as given. Scored this way the reference tracks give
  0.0566 m (intel, 2 984 relations), 0.0581 m (fr079, 1 685) and 0.0767 m (mit-csail, 1 172),
  the figures of the data's README. (fr079's figure drops to 0.0455 m with
  ``frame_offset=(0.04, 0, 0)``; we do not apply it, to stay comparable with the published
  numbers.)
"""

from service.adapters.logs.reader import log_format, read_log
from service.adapters.logs.reference import ReferenceTrack, attach_reference, load_reference
from service.adapters.logs.relations import (
    Relations,
    RelationsError,
    load_relations,
    relations_error,
)
from service.adapters.logs.scan import LogInfo, LogScan

__all__ = [
    "LogInfo",
    "LogScan",
    "ReferenceTrack",
    "Relations",
    "RelationsError",
    "attach_reference",
    "load_reference",
    "load_relations",
    "log_format",
    "read_log",
    "relations_error",
]
