"""Options of the ROS 2 front (``python -m service.ros2`` and ``python -m service --ros2``).

Frame names follow nav2's AMCL parameters (``global_frame_id``, ``odom_frame_id``,
``base_frame_id``, ``transform_tolerance``); the domain is ``--ros-domain-id``, else the
``ROS_DOMAIN_ID`` environment variable, else 0, as for a ROS 2 node.
"""

from __future__ import annotations

import argparse
import os
from collections.abc import Mapping
from dataclasses import dataclass, field

from schemas.keys import id_error, validate_prefix
from schemas.messages import METHODS
from schemas.ros2.cdr import frame_name
from schemas.ros2.graph import check_name
from service.errors import InvalidMessage


def domain_from_env(environ: Mapping[str, str] | None = None) -> int:
    """``ROS_DOMAIN_ID`` as a ROS 2 node reads it (unset or empty: 0)."""
    raw = (os.environ if environ is None else environ).get("ROS_DOMAIN_ID", "").strip()
    if not raw:
        return 0
    if not raw.isdigit():
        raise InvalidMessage(f"ROS_DOMAIN_ID: {raw[:40]!r} is not a non-negative integer")
    return int(raw)


@dataclass(frozen=True)
class Ros2Options:
    """How the front speaks ROS 2 (see docs/ros2.md; times in seconds)."""

    domain_id: int = 0
    prefix: str = "shapeloc"
    #: Robot id of a robot publishing without a namespace (``/scan``).
    default_robot_id: str = "robot"
    #: Name of the front's node in each robot's namespace (``ros2 node list``).
    node_name: str = "shapeloc"
    global_frame_id: str = "map"
    odom_frame_id: str = "odom"
    base_frame_id: str = "base_link"
    #: ``map -> odom`` is stamped this much after the scan (AMCL's ``transform_tolerance``).
    transform_tolerance: float = 1.0
    #: Method of a robot configured from ROS (no shapeloc configuration).
    method: str = "shape"
    #: Map id under which ``/map`` (no namespace) is imported; ``/<ns>/map`` is imported under
    #: the robot's id.
    global_map_id: str = "ros-map"
    #: Import ``/map`` and ``/<ns>/map`` for robots without a shapeloc configuration.
    import_maps: bool = True
    #: How long a scan may wait for its transforms or its robot's configuration.
    scan_wait: float = 2.0
    #: How long after a robot's first scan, without any odometry seen, scans go without it.
    odom_wait: float = 0.5
    #: Most scans of one robot waiting at once (the oldest is dropped beyond).
    max_pending: int = 50
    #: Namespaces declared at start (tokens and configuration look-up before any data).
    namespaces: tuple[str, ...] = field(default_factory=tuple)

    def __post_init__(self) -> None:
        if isinstance(self.domain_id, bool) or not isinstance(self.domain_id, int):
            raise InvalidMessage(f"ros domain id: {self.domain_id!r} is not an integer")
        if self.domain_id < 0:
            raise InvalidMessage(f"ros domain id: {self.domain_id} is negative")
        validate_prefix(self.prefix)
        for what, value in (("default robot id", self.default_robot_id),
                            ("global map id", self.global_map_id)):  # fmt: skip
            problem = id_error(value)
            if problem is not None:
                raise InvalidMessage(f"ros {what}: {problem}")
        check_name("/" + self.node_name, "ros node name")
        for what in ("global_frame_id", "odom_frame_id", "base_frame_id"):
            object.__setattr__(self, what, frame_name(what, getattr(self, what)))
        if self.method not in METHODS:
            raise InvalidMessage(f"ros method: {self.method!r} is not one of {', '.join(METHODS)}")
        for what in ("transform_tolerance", "scan_wait", "odom_wait"):
            v = getattr(self, what)
            if not (isinstance(v, (int, float)) and 0.0 <= v <= 3600.0):
                raise InvalidMessage(f"ros {what}: {v!r} is not in [0, 3600] s")
        if self.max_pending < 1:
            raise InvalidMessage(f"ros max_pending: {self.max_pending} < 1")
        for ns in self.namespaces:
            check_name(ns, "ros namespace")


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The ``--ros-*`` options (shared by ``python -m service.ros2`` and ``--ros2``)."""
    g = p.add_argument_group("ROS 2 (rmw_zenoh)")
    g.add_argument("--ros-domain-id", type=int, help="ROS domain id (default: ROS_DOMAIN_ID or 0)")
    g.add_argument("--ros-default-robot", help="robot id of a robot without namespace (robot)")
    g.add_argument("--ros-node-name", help="name of the front's node in each namespace")
    g.add_argument("--ros-global-frame", help="global_frame_id (map)")
    g.add_argument("--ros-odom-frame", help="odom_frame_id (odom)")
    g.add_argument("--ros-base-frame", help="base_frame_id (base_link)")
    g.add_argument("--ros-transform-tolerance", type=float, help="s added to map->odom (1.0)")
    g.add_argument("--ros-method", choices=METHODS, help="method of ROS-configured robots")
    g.add_argument("--ros-global-map-id", help="map id of an imported /map (ros-map)")
    g.add_argument(
        "--ros-no-map-import", action="store_true", default=None, help="do not import ROS maps"
    )
    g.add_argument(
        "--ros-namespace",
        action="append",
        metavar="NS",
        help="a robot namespace to announce at start (repeatable; others are found by data)",
    )


def options_from_args(args: argparse.Namespace, prefix: str | None = None) -> Ros2Options:
    """:class:`Ros2Options` from parsed ``--ros-*`` arguments (unset: defaults)."""
    values: dict[str, object] = {}
    pairs = {
        "ros_default_robot": "default_robot_id",
        "ros_node_name": "node_name",
        "ros_global_frame": "global_frame_id",
        "ros_odom_frame": "odom_frame_id",
        "ros_base_frame": "base_frame_id",
        "ros_transform_tolerance": "transform_tolerance",
        "ros_method": "method",
        "ros_global_map_id": "global_map_id",
    }
    for arg, name in pairs.items():
        if getattr(args, arg, None) is not None:
            values[name] = getattr(args, arg)
    dom = getattr(args, "ros_domain_id", None)
    values["domain_id"] = domain_from_env() if dom is None else dom
    if getattr(args, "ros_no_map_import", None):
        values["import_maps"] = False
    if getattr(args, "ros_namespace", None):
        values["namespaces"] = tuple(args.ros_namespace)
    if prefix is not None:
        values["prefix"] = prefix
    return Ros2Options(**values)  # type: ignore[arg-type]


def options_from_settings(settings: object) -> Ros2Options:
    """:class:`Ros2Options` of the service's settings (``ros_domain_id``, ``prefix`` and the
    ``ros_options`` table of the configuration file or ``SHAPELOC_ROS_OPTIONS``)."""
    extra = dict(getattr(settings, "ros_options", None) or {})
    known = set(Ros2Options.__dataclass_fields__)
    unknown = sorted(set(extra) - known)
    if unknown:
        raise InvalidMessage(f"ros_options: unknown option(s) {', '.join(unknown)}")
    if "namespaces" in extra:
        extra["namespaces"] = tuple(extra["namespaces"])
    dom = getattr(settings, "ros_domain_id", None)
    extra["domain_id"] = domain_from_env() if dom is None else dom
    extra["prefix"] = getattr(settings, "prefix", "shapeloc")
    return Ros2Options(**extra)
