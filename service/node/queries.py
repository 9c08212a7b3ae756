"""The read side of the service: answers to ``get`` on maps, poses and health.

Pure functions of the node's in-memory view (:class:`service.node.node.ServiceNode`); the node's
query thread calls :func:`answer` for each queued query. Every reply carries a concrete key;
a ``get`` on one concrete key that has nothing to return gets a ``reply_err`` saying why.
"""

from __future__ import annotations

from collections import Counter
from typing import TYPE_CHECKING, Any

import numpy as np

from schemas import codec, keys
from schemas.messages import Health, PoseMsg
from service import __version__

if TYPE_CHECKING:
    from service.node.node import ServiceNode

_MSGPACK = codec.MSGPACK_ENCODING


def answer(node: ServiceNode, query: Any) -> None:
    """Reply to one ``get`` on maps, a robot pose, the health key or this instance's state."""
    z = node.zenoh
    ke = query.key_expr
    p = node.prefix
    health_key = keys.health_key(p)
    if ke.intersects(z.KeyExpr(health_key)):
        query.reply(health_key, codec.encode(health(node)), encoding=_MSGPACK)
    if ke.intersects(z.KeyExpr(keys.maps_wildcard(p))):
        with node.lock:
            items = [(mid, m) for mid, (m, _md) in node.maps.items()]
        hits = 0
        for mid, m in items:
            k = keys.map_key(p, mid)
            if ke.intersects(z.KeyExpr(k)):
                query.reply(k, codec.encode(m), encoding=_MSGPACK)
                hits += 1
        if hits == 0 and "*" not in str(ke):
            query.reply_err(f"unknown map: no map stored under {ke}".encode())
    if ke.intersects(z.KeyExpr(keys.robots_wildcard(p, "pose"))):
        with node.lock:
            robots = list(node.configs)
            poses = dict(node.poses)
        hits = 0
        for rid in robots:
            k = keys.robot_key(p, rid, "pose")
            if ke.intersects(z.KeyExpr(k)) and rid in poses:
                query.reply(k, codec.encode(poses[rid]), encoding=_MSGPACK)
                hits += 1
        if hits == 0 and "*" not in str(ke):
            parts = str(ke).split("/")
            rid = parts[-2] if len(parts) >= 2 else ""
            if not node.serves(rid):
                return  # another shard answers for this robot
            if rid in robots:
                query.reply_err(f"robot {rid!r} has no estimate yet".encode())
            elif node.mirror.known(rid):
                query.reply_err(
                    f"robot {rid!r} is being handed over to this instance; retry".encode()
                )
            else:
                query.reply_err(f"unknown robot {rid!r}".encode())
    if ke.intersects(z.KeyExpr(keys.state_selector(p, node.instance_id))):
        answer_state(node, query)


def answer_state(node: ServiceNode, query: Any) -> None:
    """``get <prefix>/service/state/<this instance>/...``: the configuration and last pose
    (with the odometry reading of its scan) of every robot this instance knows, served or
    mirrored, for instances catching up (:mod:`service.node.cluster`)."""
    z = node.zenoh
    ke = query.key_expr
    p, me = node.prefix, node.instance_id
    with node.lock:
        served = [
            (rid, cfg, node.poses.get(rid), node.odoms.get(rid))
            for rid, cfg in node.configs.items()
        ]
    for rid, cfg, pm, odom in [*served, *node.mirror.snapshot()]:
        k = keys.state_key(p, me, "config", rid)
        if ke.intersects(z.KeyExpr(k)):
            query.reply(k, codec.encode(cfg), encoding=_MSGPACK)
        k = keys.state_key(p, me, "pose", rid)
        if pm is not None and ke.intersects(z.KeyExpr(k)):
            if pm.odom is None and odom is not None:
                pm = PoseMsg.parse({**pm.to_wire(), "odom": list(odom)})
            query.reply(k, codec.encode(pm), encoding=_MSGPACK)


def health(node: ServiceNode) -> Health:
    """Current health message (counts over this instance's robots).

    ``errors`` holds rejections per ``<message>.<ErrorClass>`` plus the service's own
    counters: ``scan.Skipped`` (valid scans replaced by a newer valid one before being
    computed: latest wins), ``worker.Restarted`` and ``state.Reset`` (state file moved aside
    by ``--reset-state``). ``ready``, ``maps_ready`` and ``maps_indexed``: see
    :mod:`service.node.readiness`; ``scan_cpu_ms``: the CPU per processed scan (service
    threads and worker) over the last scans.
    """
    ready, maps_ready, maps_indexed = node.readiness.snapshot()
    cpu = np.array(node.scan_cpu_ms, dtype=np.float64)  # a copy: the link threads append
    cpu_stats = None
    if cpu.size:
        cpu_stats = {
            "p50": float(np.percentile(cpu, 50)),
            "p99": float(np.percentile(cpu, 99)),
            "mean": float(cpu.mean()),
            "n": float(cpu.size),
        }
    with node.lock:
        by_status = Counter(p.status for p in node.poses.values())
        errors = dict(node.errors)
        skipped = sum(lk.slots.skipped for lk in node.links) + node.intake.queue.superseded
        if skipped:
            errors["scan.Skipped"] = skipped
        return Health(
            status="ok",
            version=__version__,
            robots=len(node.configs),
            maps=len(node.maps),
            scans_processed=node.scans_processed,
            scans_rejected=node.scans_rejected,
            instance_id=node.instance_id,
            uptime_s=node.uptime_s(),
            errors=errors,
            robots_by_status=dict(by_status),
            ready=ready,
            maps_ready=maps_ready,
            maps_indexed=maps_indexed,
            scan_cpu_ms=cpu_stats,
        )
