"""A ROS 2 node on a Zenoh session, as rmw_zenoh makes one: liveliness tokens for the node
and each of its publishers and subscriptions, publishers that attach rmw_zenoh's attachment
to every sample, transient-local publishers with a cache that late joiners query (Zenoh's
advanced publisher, as rmw_zenoh_cpp since Jazzy 0.2.x), transient-local subscriptions that
query it (advanced subscriber with history).

Used by the front (:mod:`service.ros2.front`) and by the simulator's ROS 2 robots
(:mod:`sim_publisher.ros2`).
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import zenoh
import zenoh.ext as zx

from schemas.ros2 import graph
from schemas.ros2.attachment import Attachment, encode_attachment
from schemas.ros2.types import RosType

#: rmw_zenoh's heartbeat period (s) of a reliable transient-local publisher (sporadic).
HEARTBEAT_S = 0.5


class EntityCounter:
    """Node and entity ids of one session (rmw_zenoh: one counter per context, from 0)."""

    def __init__(self) -> None:
        self._it = itertools.count()
        self._lock = threading.Lock()

    def next(self) -> int:
        with self._lock:
            return next(self._it)


def reliability_of(qos: graph.QoS) -> zenoh.Reliability:
    """Zenoh reliability of a QoS (rmw_zenoh: reliable QoS -> reliable)."""
    if qos.reliability == graph.RELIABLE:
        return zenoh.Reliability.RELIABLE
    return zenoh.Reliability.BEST_EFFORT


@dataclass
class RosPublisher:
    """One ROS 2 publisher: Zenoh publisher, liveliness token, GID, next sequence number."""

    key: str
    pub: Any
    token: Any
    gid: bytes
    seq: int = 1

    def put(self, payload: bytes) -> None:
        """Publish CDR bytes with the attachment (sequence number from 1, now, GID)."""
        att = Attachment(self.seq, time.time_ns(), self.gid)
        self.seq += 1
        self.pub.put(payload, attachment=encode_attachment(att))

    def undeclare(self) -> None:
        for e in (self.token, self.pub):
            with contextlib.suppress(Exception):
                e.undeclare()


class RosNode:
    """Node ``name`` in ``namespace`` on ``session`` (ids from ``counter``)."""

    def __init__(
        self,
        session: zenoh.Session,
        domain_id: int,
        namespace: str,
        name: str,
        counter: EntityCounter,
    ) -> None:
        self.session = session
        self.domain_id = domain_id
        self.counter = counter
        self.info = graph.NodeInfo(domain_id, str(session.zid()), counter.next(), namespace, name)
        self._decl: list[Any] = [self._token(graph.node_token(self.info))]
        self._pubs: list[RosPublisher] = []

    def _token(self, key: str) -> Any:
        return self.session.liveliness().declare_token(key)

    def topic(self, name: str) -> str:
        """Fully qualified name of a relative (``scan``) or absolute (``/map``) topic."""
        return name if name.startswith("/") else graph.join_name(self.info.namespace, name)

    def publisher(self, name: str, rtype: RosType, qos: graph.QoS) -> RosPublisher:
        """A publisher of ``rtype`` on topic ``name`` with ``qos`` (token declared)."""
        topic = self.topic(name)
        token = graph.endpoint_token(self.info, self.counter.next(), "MP", topic, rtype, qos)
        key = graph.topic_key(self.domain_id, topic, rtype)
        cc = (
            zenoh.CongestionControl.BLOCK
            if qos.reliability == graph.RELIABLE and qos.history == graph.KEEP_ALL
            else zenoh.CongestionControl.DROP
        )
        if qos.durability == graph.TRANSIENT_LOCAL:
            kwargs: dict[str, Any] = {}
            if qos.reliability == graph.RELIABLE:
                kwargs["sample_miss_detection"] = zx.MissDetectionConfig(
                    sporadic_heartbeat=HEARTBEAT_S
                )
            pub = zx.declare_advanced_publisher(
                self.session,
                key,
                cache=zx.CacheConfig(max_samples=qos.depth),
                publisher_detection=True,
                reliability=reliability_of(qos),
                congestion_control=cc,
                **kwargs,
            )
        else:
            pub = self.session.declare_publisher(
                key, reliability=reliability_of(qos), congestion_control=cc
            )
        out = RosPublisher(key, pub, self._token(token), graph.gid_of(token))
        self._pubs.append(out)
        return out

    def subscription_token(self, name: str, rtype: RosType, qos: graph.QoS) -> None:
        """Only the graph's view of a subscription (its data arrive by another subscriber)."""
        topic = self.topic(name)
        tok = graph.endpoint_token(self.info, self.counter.next(), "MS", topic, rtype, qos)
        self._decl.append(self._token(tok))

    def subscriber(
        self, name: str, rtype: RosType, qos: graph.QoS, callback: Callable[[Any], None]
    ) -> None:
        """A subscription of topic ``name`` (token declared; transient local -> history)."""
        self.subscription_token(name, rtype, qos)
        self._decl.append(
            subscribe(
                self.session,
                graph.topic_key(self.domain_id, self.topic(name), rtype),
                qos,
                callback,
            )
        )

    def close(self) -> None:
        """Undeclare every publisher, subscriber and token of the node."""
        for p in self._pubs:
            p.undeclare()
        for d in reversed(self._decl):
            with contextlib.suppress(Exception):
                d.undeclare()
        self._pubs.clear()
        self._decl.clear()


def subscribe(
    session: zenoh.Session,
    key_expr: str,
    qos: graph.QoS,
    callback: Callable[[Any], None],
    remote_only: bool = False,
) -> Any:
    """A Zenoh subscriber as rmw_zenoh declares one for ``qos`` (transient local: advanced
    subscriber with history of ``depth`` samples, late publishers detected, recovery on
    heartbeat when reliable)."""
    origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY
    if qos.durability != graph.TRANSIENT_LOCAL:
        return session.declare_subscriber(key_expr, callback, allowed_origin=origin)
    kwargs: dict[str, Any] = {}
    if qos.reliability == graph.RELIABLE:
        kwargs["recovery"] = zx.RecoveryConfig(heartbeat=True)
    return zx.declare_advanced_subscriber(
        session,
        key_expr,
        callback,
        history=zx.HistoryConfig(detect_late_publishers=True, max_samples=qos.depth),
        subscriber_detection=True,
        allowed_origin=origin,
        **kwargs,
    )
