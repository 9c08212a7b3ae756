"""Several service instances on one key prefix: who serves which robot, and what they share.

Design (docs/cluster.md has the why and the figures):

* **Membership** is Zenoh liveliness: every instance declares ``<prefix>/service/alive/<id>``
  and, with ``shard = "hash"``, subscribes to the other instances' tokens (with history). A
  token vanishes a few milliseconds after its process dies (the router sees the link close).
* **Ownership**: with ``shard = "static"`` an instance serves the robot ids its ``robots``
  key expression matches; with ``shard = "hash"`` the owner of a robot is the live instance
  with the highest rendezvous weight ``blake2b(instance_id, robot_id)``
  (:func:`hrw_owner`). When an instance leaves, only its robots move (to the survivors);
  when one joins, only the robots it now wins move (to it).
* **Shared state, through Zenoh itself**: every instance already receives every map, robot
  configuration and pose on its ``<prefix>/**`` subscriber. Besides serving its own robots it
  keeps a :class:`Mirror` of the others: their configurations (committed to its own SQLite
  store) and the last pose each owner published (kept as bytes, decoded at most once per
  save interval or at takeover; the pose carries the odometry reading of its scan). So a
  survivor takes a dead instance's robots over from its own memory, at the last *published*
  pose, without reading anybody's files.
* **Catching up**: an instance that (re)starts while others are alive asks them
  (``get <prefix>/maps/*`` and ``get <prefix>/service/state/*/**``, the latter answered by
  every instance with the configs and last poses it knows) and merges the answers into its
  store before restoring; the instances already running pull a joiner's state the same way
  (robots they have never seen are added). A joiner waits ``handover_delay_s`` after
  declaring its token before taking its share, so the previous owners have let go.
* **Isolation**: an instance that loses its router sees every other token vanish. It takes
  nobody over while it is cut off (its own token is gone, or it has no router and no peer),
  and after reconnecting it waits until the others' tokens are back before acting on losses.

Zenoh callbacks only queue events or copy bytes; the membership thread does the work.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from schemas import keys
from schemas.messages import PoseMsg, RobotConfig
from service.errors import ShapelocError, StateError
from service.node.catchup import Fetched, fetch_state, merge_into_store
from service.node.mirror import MAX_POSE_BYTES, Mirror, fresher, hrw_owner, odom_of, pose_matches
from service.node.state import StateStore
from service.node.workers import config_request

if TYPE_CHECKING:
    from service.node.assignment import Assignment
    from service.node.scheduler import WorkerLink
    from service.node.settings import ServiceSettings

log = logging.getLogger("shapeloc.service")

_STALL_S = 1.0  # a membership-loop turn this much later than its wait: the process stalled


@dataclass(frozen=True)
class _View:
    """The member set ownership is computed over, with its per-robot answers cached."""

    members: frozenset[str]
    cache: dict[str, bool] = field(default_factory=dict, compare=False)


class ClusterPlane:
    """Ownership, the mirror and membership, mixed into :class:`service.node.node.ServiceNode`
    (which owns the attributes declared here)."""

    settings: ServiceSettings
    session: Any
    zenoh: Any
    prefix: str
    instance_id: str
    lock: threading.RLock
    stopping: threading.Event
    maps: dict[str, Any]
    configs: dict[str, RobotConfig]
    poses: dict[str, PoseMsg]
    odoms: dict[str, tuple[float, float, float]]
    errors: Counter[str]
    state: StateStore | None
    links: list[WorkerLink]
    assignment: Assignment
    _control_mutex: threading.RLock
    _dirty: set[str]
    _entities: list[Any]
    _threads: list[threading.Thread]

    def _link_of(self, robot_id: str) -> WorkerLink:
        raise NotImplementedError

    # ------------------------------------------------------------------ ownership
    def _init_cluster(self) -> None:
        self.mirror = Mirror(self.settings.max_robots)
        self._robots_ke = self.zenoh.KeyExpr(self.settings.robots)
        self._view = _View(frozenset({self.instance_id}))
        self._member_q: queue.SimpleQueue[tuple[bool, str]] = queue.SimpleQueue()
        self._join_at = 0.0
        self._cut_poses: dict[str, PoseMsg] = {}  # our poses when we were last cut off
        #: robots whose scans are dropped from being cut off until compared with the others
        self.suspended: frozenset[str] = frozenset()

    @property
    def hashing(self) -> bool:
        """Whether robots are spread by rendezvous hashing over the live instances."""
        return self.settings.shard == "hash"

    @property
    def clustered(self) -> bool:
        """Whether this instance is meant to be one of several (hash shard or a pattern)."""
        return self.hashing or self.settings.robots != "**"

    def members(self) -> frozenset[str]:
        """The instances ownership is currently computed over."""
        return self._view.members

    def serves(self, robot_id: str) -> bool:
        """Whether this instance serves ``robot_id`` now (``robots`` pattern; with hash
        sharding, highest rendezvous weight among the members)."""
        view = self._view
        hit = view.cache.get(robot_id)
        if hit is None:
            hit = self._owns(robot_id, view.members)
            if len(view.cache) < 100_000:
                view.cache[robot_id] = hit
        return hit

    def _owns(self, robot_id: str, members: frozenset[str]) -> bool:
        if self.hashing:
            return hrw_owner(robot_id, members) == self.instance_id
        try:
            return bool(self._robots_ke.intersects(self.zenoh.KeyExpr(robot_id)))
        except Exception:
            return True  # invalid ids are rejected (with a notice) further on

    # ------------------------------------------------------------------ mirror input
    def _on_pose_sample(self, sample: Any, robot_id: str) -> None:
        """Zenoh callback: another instance published a pose; keep its bytes if we mirror the
        robot (our own poses come back here too and are ignored)."""
        if not self.mirror.known(robot_id) or len(sample.payload) > MAX_POSE_BYTES:
            return
        if sample.kind != self.zenoh.SampleKind.PUT:
            return
        enc = None if sample.encoding is None else str(sample.encoding)
        self.mirror.offer_raw(robot_id, sample.payload.to_bytes(), enc)

    def mirror_config(self, robot_id: str, cfg: RobotConfig | None) -> None:
        """Control thread: another instance's robot was configured (``cfg``) or deleted
        (``None``). Committed to the store; invalid or unplaceable ones are ignored quietly:
        the owner sends the notice."""
        assert self.state is not None
        if cfg is None:
            if self.mirror.forget(robot_id):
                self.state.delete_robot(robot_id)
                log.debug("mirrored robot %s removed", robot_id)
            return
        with self.lock:
            if cfg.map_id not in self.maps:
                return
        if not self.mirror.set_config(robot_id, cfg):
            with self.lock:
                self.errors["cluster.MirrorFull"] += 1
            return
        self.state.put_robot(robot_id, cfg.to_wire())

    # ------------------------------------------------------------------ start-up
    def _live_peers(self) -> frozenset[str]:
        """Ids of the other instances whose liveliness token is visible now."""
        t = self.settings.catchup_timeout_s
        deadline = time.monotonic() + t
        if self.settings.connect or self.settings.mode == "client":
            while not self._linked() and time.monotonic() < deadline:
                time.sleep(0.02)
        out = set()
        for reply in self.session.liveliness().get(keys.alive_wildcard(self.prefix), timeout=t):
            if reply.ok is None:
                continue
            with contextlib.suppress(ShapelocError):
                out.add(keys.parse_alive_key(self.prefix, str(reply.ok.key_expr)))
        out.discard(self.instance_id)
        return frozenset(out)

    def _fetch_answered(self, expected: frozenset[str], with_maps: bool, when: str) -> Fetched:
        """:func:`fetch_state` of every instance, asked again (every 0.1 s, within
        ``catchup_timeout_s``) until each of ``expected`` (instances whose tokens are live)
        has answered; returns the last answer (those still silent are logged, ``when``
        saying at which step). Right after a token appears the router may not route to that
        instance yet (a CI run that asked 0.23 s after a reconnection restarted 1 of the 2
        robots the others had served). An instance that knows no robot sends no state, so
        with one the asking takes that long."""
        deadline = time.monotonic() + self.settings.catchup_timeout_s
        while True:
            f = fetch_state(
                self.session,
                self.prefix,
                "*",
                self.instance_id,
                self.settings.catchup_timeout_s,
                with_maps=with_maps,
            )
            silent = expected - f.instances - {self.instance_id}
            if not silent or time.monotonic() >= deadline or self.stopping.is_set():
                break
            time.sleep(0.1)
        if silent:
            log.warning(
                "cluster: %s, no state from %s within %.1f s; going on without it",
                when,
                ", ".join(sorted(silent)),
                self.settings.catchup_timeout_s,
            )
        return f

    def _catch_up(self) -> frozenset[str]:
        """Before restoring: if other instances are alive, merge their maps, robot configs
        and last poses into the store (:func:`merge_into_store`); returns their ids."""
        if not self.clustered:
            return frozenset()
        assert self.state is not None
        try:
            peers = self._live_peers()
            if not peers:
                log.info("cluster: no other instance alive; starting from the own state")
                return peers
            t0 = time.monotonic()
            f = self._fetch_answered(peers, with_maps=True, when="catching up")
        except StateError:
            raise
        except Exception as e:  # no liveliness/get (old router, access control): go on alone
            log.warning("cluster: catch-up skipped: %s: %s", type(e).__name__, e)
            return frozenset()
        changed = merge_into_store(self.state, f)
        log.info(
            "cluster: caught up from %s in %.2f s: %d maps, %d robots, %d poses known; "
            "stored %s; %d invalid replies",
            sorted(f.instances) or sorted(peers),
            time.monotonic() - t0,
            len(f.maps),
            len(f.configs),
            len(f.poses),
            dict(changed) or "nothing new",
            f.invalid,
        )
        return peers

    def _warm_workers(self) -> None:
        """One of several instances: before it is visible, let every worker build a
        localiser for each (method, map) of the mirrored robots once and drop it, so that
        taking robots over later does not pay the first-use cost (numba kernels, caches:
        about 1.4 s for ``shape``, 0.4 s for ``icp`` on the office map)."""
        if not self.clustered:
            return
        t0 = time.monotonic()
        seen: dict[tuple[str, str], list[float]] = {}
        for _rid, cfg, pm, _odom in self.mirror.snapshot():
            start = pm.pose if pm is not None else cfg.initial_pose
            if start is not None and cfg.map_id in self.maps:
                seen.setdefault((cfg.method, cfg.map_id), [float(v) for v in start])
        t = self.settings.worker_timeout_s
        for (method, map_id), start in seen.items():
            for link in self.links:  # "~" is never in a robot id: no collision possible
                link.worker.call(("config", "~warm-up", method, map_id, start, None, None), t)
                link.worker.call(("forget", "~warm-up"), t)
        if seen:
            log.info(
                "cluster: workers warmed up for %s in %.2f s",
                sorted(f"{m}@{mid}" for m, mid in seen),
                time.monotonic() - t0,
            )

    def _init_view(self, peers: frozenset[str]) -> None:
        """Members before restoring: alone, this instance; with live peers (hash sharding),
        only them, so it takes its share only after they see its token (``_join``)."""
        if self.hashing and peers:
            self._view = _View(peers)
        else:
            self._view = _View(frozenset({self.instance_id}))

    def _declare_membership(self) -> None:
        """After the token: watch the instances' tokens (hash sharding) from a thread."""
        if not self.hashing:
            return
        self._join_at = time.monotonic() + self.settings.handover_delay_s
        sub = self.session.liveliness().declare_subscriber(
            keys.alive_wildcard(self.prefix), self._on_alive, history=True
        )
        self._entities.append(sub)
        t = threading.Thread(target=self._membership_loop, name="shapeloc-members", daemon=True)
        self._threads.append(t)
        t.start()

    def _on_alive(self, sample: Any) -> None:
        """Zenoh callback: queue a token appearing or vanishing."""
        self._member_q.put((sample.kind == self.zenoh.SampleKind.PUT, str(sample.key_expr)))

    # ------------------------------------------------------------------ membership
    def _linked(self) -> bool:
        try:
            info = self.session.info
            return bool(list(info.routers_zid()) or list(info.peers_zid()))
        except Exception:
            return True

    def _isolated(self, own_seen: bool) -> bool:
        """Cut off from the others: our own token is not visible (client mode: it comes back
        through the router), or we were told to connect and have neither router nor peer."""
        if not own_seen:
            return True
        if self.settings.connect or self.settings.mode == "client":
            return not self._linked()
        return False

    def _membership_loop(self) -> None:
        me = self.instance_id
        live: set[str] = set(self._view.members) - {me}
        own_seen = own_ever = False  # our own token visible now / ever
        lost_at: float | None = None  # act on vanished tokens from then on
        settle_at: float | None = None  # after isolation: wait for the tokens to come back
        refresh_at: float | None = None  # after isolation: take newer poses of our robots
        was_isolated = False
        reconnect_s = 2 * self.settings.reconnect_max_ms / 1000.0
        # Our poses as of the last loop turn that ran on time. A frozen process (SIGSTOP, a
        # suspended VM) learns it was cut off only after it runs again, and by then it may
        # have computed poses from fresh scans with its stale localiser; those must not count
        # as newer than what the others computed while we were away (a CI run restarted only
        # 1 of 2 robots). After a stall the snapshot is held for a while.
        on_time_poses: dict[str, PoseMsg] = {}
        hold_until = 0.0
        while not self.stopping.is_set():
            now = time.monotonic()
            due = [d for d in (lost_at, settle_at, refresh_at) if d is not None]
            if me not in self._view.members:
                due.append(self._join_at)
            wait = min([0.5, *(max(0.0, d - now) for d in due)])
            events: list[tuple[bool, str]] = []
            with contextlib.suppress(queue.Empty):
                events.append(self._member_q.get(timeout=wait))
            with contextlib.suppress(queue.Empty):
                while True:
                    events.append(self._member_q.get_nowait())
            stalled = time.monotonic() - now - wait
            if stalled > _STALL_S:
                log.warning("cluster: this process did not run for %.1f s (frozen?)", stalled)
                hold_until = time.monotonic() + reconnect_s + self.settings.takeover_grace_s
            cut = False  # our own token vanished (even if it is back in the same batch)
            for put, key in events:
                try:
                    inst = keys.parse_alive_key(self.prefix, key)
                except ShapelocError:
                    continue  # not an instance token: ignored
                if inst == me:
                    own_seen = put
                    cut = cut or (own_ever and not put)
                    own_ever = own_ever or put
                elif put:
                    if inst not in live:
                        log.info("cluster: token of instance %s appeared", inst)
                    live.add(inst)
                else:
                    if inst in live:
                        log.info("cluster: token of instance %s vanished", inst)
                    live.discard(inst)
                    lost_at = lost_at or time.monotonic() + self.settings.takeover_grace_s
            now = time.monotonic()
            isolated = own_ever and self._isolated(own_seen)
            if (isolated or cut) and not was_isolated:
                log.warning("cluster: cut off from the other instances; taking nobody over")
                with self.lock:  # what we knew when cut off (a frozen process learns it late)
                    self._cut_poses = dict(on_time_poses)
                    # until compared with what the others did meanwhile, no pose from them
                    self.suspended = frozenset(self.configs)
                was_isolated = True
            if was_isolated and not isolated:
                settle_at = now + reconnect_s + self.settings.takeover_grace_s
                refresh_at = now + self.settings.handover_delay_s
                log.warning("cluster: reconnected; waiting %.1f s for the tokens", reconnect_s)
            was_isolated = isolated
            if refresh_at is not None and now >= refresh_at and not isolated:
                refresh_at = None
                try:
                    self._refresh_served(frozenset(live))
                except Exception as e:
                    log.warning("cluster: could not compare poses after reconnecting: %s", e)
                finally:
                    self.suspended = frozenset()
            if not was_isolated and time.monotonic() >= hold_until:
                with self.lock:
                    on_time_poses = dict(self.poses)
            members = self._view.members
            target = set(live)
            if me in members or now >= self._join_at:
                target.add(me)
            acting = (
                own_ever
                and not isolated
                and all(d is None or now >= d for d in (lost_at, settle_at))
            )
            if acting:
                lost_at = settle_at = None
            else:
                target |= members  # keep the vanished ones until it is safe to act
            if frozenset(target) != members:
                try:
                    self._change_members(frozenset(target))
                except Exception:
                    log.exception("cluster: membership change to %s failed", sorted(target))

    def _change_members(self, target: frozenset[str]) -> None:
        old = self._view.members
        joined = sorted(target - old - {self.instance_id})
        for inst in joined:  # robots a joiner knows and we do not (it was up when we were not)
            try:
                f = fetch_state(
                    self.session,
                    self.prefix,
                    inst,
                    self.instance_id,
                    self.settings.catchup_timeout_s,
                    with_maps=False,
                )
                self._merge_running(f)
            except StateError as e:
                log.error("cluster: could not store what %s knows: %s", inst, e)
            except Exception as e:
                log.warning("cluster: could not ask %s for its state: %s", inst, e)
        self.rebalance(target)

    def _refresh_served(self, expected: frozenset[str]) -> None:
        """After being cut off (frozen, partitioned): the others may have served our robots
        meanwhile and let go when our token came back. Each robot for which another instance
        knows a pose newer than ours when we were cut off restarts from that pose (ours may
        have been computed since from the stale localiser); robots configured meanwhile are
        learnt. ``expected``: the instances whose tokens are live, each heard from
        (:meth:`_fetch_answered`)."""
        f = self._fetch_answered(expected, with_maps=False, when="after reconnecting")
        self._merge_running(f)
        with self._control_mutex:
            newer = []
            with self.lock:
                for rid, pm in f.poses.items():
                    cfg = self.configs.get(rid)
                    if cfg is None or f.configs.get(rid) != cfg or not pose_matches(pm, rid, cfg):
                        continue
                    if fresher(pm, self._cut_poses.get(rid)):
                        self.poses[rid] = pm
                        self.odoms.pop(rid, None)
                        if (o := odom_of(pm)) is not None:
                            self.odoms[rid] = o
                        self._dirty.add(rid)
                        newer.append((rid, cfg, pm))
            waits = []
            for rid, cfg, pm in newer:
                odom = odom_of(pm)
                req = config_request(
                    rid, cfg, [float(v) for v in pm.pose], None if odom is None else list(odom)
                )
                waits.append(self._link_of(rid).submit(req))
            for fut in waits:
                with contextlib.suppress(Exception):
                    fut.result(timeout=self.settings.reply_wait_s)
        log.info(
            "cluster: after reconnecting, %d of our robots restart from a newer pose known "
            "elsewhere (%s)",
            len(newer),
            ", ".join(r for r, *_ in newer[:8]),
        )

    def _merge_running(self, f: Fetched) -> None:
        """Add robots we have never seen; take newer poses of mirrored ones."""
        with self._control_mutex:
            added = 0
            for rid, cfg in f.configs.items():
                with self.lock:
                    if rid in self.configs:
                        continue
                if not self.mirror.known(rid):
                    self.mirror_config(rid, cfg)
                    added += self.mirror.known(rid)
                pm = f.poses.get(rid)
                if pm is not None and self.mirror.known(rid) and self.mirror.configs[rid] == cfg:
                    self.mirror.offer_pose(rid, pm)
            if added:
                log.info("cluster: learnt %d robot configurations from a joining instance", added)

    def rebalance(self, members: frozenset[str]) -> None:
        """Recompute ownership over ``members``: hand over the robots we no longer own (into
        the mirror, at their last pose and odometry) and take over the mirrored robots we now
        own (their localiser restarts at the newest pose known)."""
        t0 = time.monotonic()
        with self._control_mutex:
            with self.lock:
                old = self._view.members
                self._view = _View(members)
                lost = [r for r in self.configs if not self.serves(r)]
                for r in lost:
                    cfg = self.configs.pop(r)
                    self.mirror.put(r, cfg, self.poses.pop(r, None), self.odoms.pop(r, None), True)
                gained = []
                for r in [r for r in self.mirror.configs if self.serves(r)]:
                    if r in self.configs:  # configured here meanwhile: that config wins
                        self.mirror.forget(r)
                        continue
                    got = self.mirror.take(r)
                    if got is None:
                        continue
                    cfg, pm, odom = got
                    self.configs[r] = cfg
                    if pm is not None:
                        self.poses[r] = pm
                        if odom is not None:
                            self.odoms[r] = odom
                    gained.append((r, cfg, pm, odom))
            waits = []
            for r in lost:
                link = self._link_of(r)
                link.slots.discard(r)
                waits.append((r, link.submit(("forget", r))))
                self.assignment.release(r)
            adopted = []
            for r, cfg, pm, odom in gained:
                link = self.links[self.assignment.assign(r)]
                start = None if pm is None else [float(v) for v in pm.pose]
                odom_start = None if start is None or odom is None else list(odom)
                req = config_request(r, cfg, start, odom_start)
                adopted.append((r, cfg, pm, odom, link.submit(req)))
            t = self.settings.reply_wait_s
            for _r, fut in waits:
                with contextlib.suppress(Exception):
                    fut.result(timeout=t)
            failed = 0
            for r, cfg, pm, odom, fut in adopted:
                try:
                    status, why = fut.result(timeout=t)
                except Exception as e:
                    status, why = "err", str(e)
                if status != "ok":
                    failed += 1
                    log.error("cluster: could not take robot %s over: %s", r, why)
                    with self.lock:
                        self.configs.pop(r, None)
                        self.poses.pop(r, None)
                        self.odoms.pop(r, None)
                    self.assignment.release(r)
                    self.mirror.put(r, cfg, pm, odom)
            with self.lock:
                self.errors["cluster.Adopted"] += len(gained) - failed
                self.errors["cluster.Released"] += len(lost)
        log.info(
            "cluster: members %s -> %s: took over %d robots%s, handed %d over, in %.0f ms",
            sorted(old),
            sorted(members),
            len(gained) - failed,
            f" ({', '.join(r for r, *_ in gained[:8])}{', ...' if len(gained) > 8 else ''})"
            if gained
            else "",
            len(lost),
            (time.monotonic() - t0) * 1e3,
        )
