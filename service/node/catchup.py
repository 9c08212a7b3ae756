"""Catching up with the other instances of a cluster: ask the live ones for the maps,
robot configurations and last poses they know (:func:`fetch_state`) and merge the answers
into the own store (:func:`merge_into_store`). The design is in :mod:`service.node.cluster`."""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from schemas import codec, keys
from schemas.limits import MAX_PAYLOAD_BYTES
from schemas.messages import Map, PoseMsg, RobotConfig
from service.errors import InvalidMessage, ShapelocError
from service.node.mirror import fresher, odom_of, pose_matches
from service.node.state import SavedPose, StateStore

if TYPE_CHECKING:
    pass

log = logging.getLogger("shapeloc.service")


@dataclass
class Fetched:
    """What other instances told a catching-up instance: maps, robot configurations and
    the newest pose per robot (each pose belongs to the configuration chosen)."""

    maps: dict[str, Map] = field(default_factory=dict)
    configs: dict[str, RobotConfig] = field(default_factory=dict)
    poses: dict[str, PoseMsg] = field(default_factory=dict)
    instances: set[str] = field(default_factory=set)
    invalid: int = 0


def _reply_sample(reply: Any) -> Any:
    ok = reply.ok
    if ok is None:
        return None
    if len(ok.payload) > MAX_PAYLOAD_BYTES:
        raise InvalidMessage(f"reply of {len(ok.payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    return ok


def fetch_state(
    session: Any, prefix: str, instance: str, me: str, timeout_s: float, with_maps: bool
) -> Fetched:
    """Ask the live instances (``instance``: one id, or ``*``) for the robots they know
    (``get <prefix>/service/state/<instance>/**``) and, with ``with_maps``, for the maps
    (``get <prefix>/maps/*``). Every reply is validated; invalid ones are counted and
    skipped. Per robot the configuration comes from the instance holding the newest pose for
    it (stamp, then seq; without any pose, the smallest instance id)."""
    import zenoh

    out = Fetched()
    cfgs: dict[str, dict[str, RobotConfig]] = {}
    poses: dict[str, dict[str, PoseMsg]] = {}
    none = zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE)
    for reply in session.get(
        keys.state_selector(prefix, instance), timeout=timeout_s, consolidation=none
    ):
        try:
            ok = _reply_sample(reply)
            if ok is None:
                continue
            inst, kind, rid = keys.parse_state_key(prefix, str(ok.key_expr))
            if inst == me:
                continue
            data, enc = ok.payload.to_bytes(), str(ok.encoding)
            if kind == "config":
                cfgs.setdefault(rid, {})[inst] = codec.decode(RobotConfig, data, enc)
            else:
                pm = codec.decode(PoseMsg, data, enc)
                if pm.robot_id != rid:
                    raise InvalidMessage(f"pose of {pm.robot_id!r} under the key of {rid!r}")
                poses.setdefault(rid, {})[inst] = pm
            out.instances.add(inst)
        except ShapelocError as e:
            out.invalid += 1
            log.debug("invalid state reply ignored: %s", e)
    for rid, by_inst in cfgs.items():
        best: tuple[str, RobotConfig, PoseMsg | None] | None = None
        for inst in sorted(by_inst):
            cfg = by_inst[inst]
            pm = poses.get(rid, {}).get(inst)
            if pm is not None and not pose_matches(pm, rid, cfg):
                pm = None
            if best is None or (pm is not None and fresher(pm, best[2])):
                best = (inst, cfg, pm)
        assert best is not None
        out.configs[rid] = best[1]
        if best[2] is not None:
            out.poses[rid] = best[2]
    if with_maps:
        for reply in session.get(keys.maps_wildcard(prefix), timeout=timeout_s):
            try:
                ok = _reply_sample(reply)
                if ok is None:
                    continue
                mid = keys.parse_map_key(prefix, str(ok.key_expr))
                m = codec.decode(Map, ok.payload.to_bytes(), str(ok.encoding))
                codec.check_key_id(m.map_id, mid, "map_id")
                out.maps[mid] = m
            except ShapelocError as e:
                out.invalid += 1
                log.debug("invalid map reply ignored: %s", e)
    return out


def merge_into_store(store: StateStore, f: Fetched) -> Counter[str]:
    """A (re)starting instance adopts what the live instances know: their maps and robot
    configurations replace its own where they differ (a changed configuration drops the saved
    pose, as a config put does), and a newer pose replaces the saved one. Nothing is deleted:
    something deleted while this instance was down stays in its store (docs/cluster.md)."""
    changed: Counter[str] = +Counter(  # (unary +: only what changed, as a count above 0)
        maps=_adopt(store.maps(), f.maps, Map, store.put_map),
        configs=_adopt(store.robots(), f.configs, RobotConfig, store.put_robot),
    )
    saved = store.poses()
    news: dict[str, SavedPose] = {}
    for rid, pm in f.poses.items():
        sp = saved.get(rid)
        if sp is None or (pm.stamp, pm.seq) > (sp.stamp, sp.seq) or sp.map_id != pm.map_id:
            x, y, th = (float(v) for v in pm.pose)
            news[rid] = SavedPose(pm.map_id, x, y, th, pm.seq, pm.stamp, pm.status, odom_of(pm))
    if news:
        store.save_poses(news)
        changed["poses"] += len(news)
    return changed


def _adopt(
    have: dict[str, Any], fetched: dict[str, Any], model: Any, put: Callable[[str, Any], None]
) -> int:
    """Store every fetched message (``model``) that ``have`` (key -> stored wire) lacks or
    holds differently, with ``put``; how many were stored."""
    n = 0
    for key, msg in fetched.items():
        wire = have.get(key)
        if wire is None or _parse_or_none(model, wire) != msg:
            put(key, msg.to_wire())
            n += 1
    return n


def _parse_or_none(model: Any, wire: Any) -> Any:
    try:
        return model.parse(wire)
    except ShapelocError:
        return None
