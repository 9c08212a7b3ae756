"""When the service calls a map ready (service/node/readiness.py, control.py, queries.py),
without a network: a stored map is listed in ``Health.maps_ready`` only once every worker has
prepared it, ``ready`` waits for that too, a map put again leaves the list until its new
version is prepared, and a deleted map leaves it. The warm-up and map preparation themselves
(service/node/prepare.py) are checked on a small room."""

from __future__ import annotations

import logging
import threading
from concurrent.futures import Future
from typing import Any

import pytest

from service.core.types import MapData
from service.node.prepare import free_pose, prepare_map, warm_up_worker
from service.node.readiness import Readiness
from service.node.workers import WorkerCore
from tests.service.node.harness import ROOM, Harness, wait_for


class _GatedMaps:
    """Wraps the in-process worker: map requests wait for ``gate``."""

    def __init__(self, inner: Any) -> None:
        self.inner, self.core = inner, inner.core
        self.gate = threading.Event()
        self.entered = threading.Event()

    def call(self, req: tuple[Any, ...], timeout_s: float | None = None) -> tuple[str, Any]:
        if req[0] == "map":
            self.entered.set()
            assert self.gate.wait(20.0)
        return self.inner.call(req, timeout_s)

    def close(self) -> None:
        self.inner.close()


def test_a_map_is_ready_only_once_every_worker_has_prepared_it(harness: Harness) -> None:
    h = harness
    wait_for(lambda: h.health().ready is True)  # warmed up, no map yet
    assert h.health().maps_ready == [] and h.health().maps_indexed is None  # no search worker
    gated = _GatedMaps(h.node.links[0].worker)
    h.node.links[0].worker = gated  # type: ignore[assignment]
    put = threading.Thread(target=h.put_map)
    put.start()
    assert gated.entered.wait(10.0)
    hl = h.health()
    # stored (counted, and a get returns it) but not ready: the worker is still preparing it
    assert hl.maps == 1 and hl.maps_ready == [] and hl.ready is False
    assert h.query("shapeloc/maps/room").replies
    gated.gate.set()
    put.join(10.0)
    hl = h.health()
    assert hl.maps_ready == ["room"] and hl.ready is True
    # a put again: the new version is not ready until prepared
    gated.gate.clear()
    gated.entered.clear()
    put = threading.Thread(target=h.put_map)
    put.start()
    assert gated.entered.wait(10.0)
    assert h.health().maps_ready == [] and h.health().ready is False
    gated.gate.set()
    put.join(10.0)
    assert h.health().maps_ready == ["room"]
    h.put("shapeloc/maps/room", b"", delete=True)
    hl = h.health()
    assert hl.maps == 0 and hl.maps_ready == [] and hl.ready is True


def test_readiness_ignores_a_preparation_of_an_older_version() -> None:
    r = Readiness(indexing=True)
    v1 = r.stored("m")
    v2 = r.stored("m")  # put again while v1 was being prepared
    r.prepared("m", v1)
    r.indexed("m", v1)
    assert r.snapshot() == (False, [], [])
    r.prepared("m", v2)
    r.indexed("m", v2)
    assert r.snapshot() == (True, ["m"], ["m"])
    pending: Future[Any] = Future()
    r.warming([pending])  # a worker still warming up
    assert r.snapshot()[0] is False
    pending.set_result(("ok", "pong"))
    assert r.snapshot()[0] is True


def test_with_a_search_worker_a_map_is_ready_only_once_its_index_build_is_over() -> None:
    """The index build is first-use work: a prepared map waits for it; a failed build makes
    the map ready without listing it indexed (its first search builds the index)."""
    r = Readiness(indexing=True)
    va, vb = r.stored("a"), r.stored("b")
    r.prepared("a", va)
    r.prepared("b", vb)
    assert r.snapshot() == (False, [], [])
    r.indexed("a", va)
    assert r.snapshot() == (False, ["a"], ["a"])
    r.indexed("b", vb, built=False)
    assert r.snapshot() == (True, ["a", "b"], ["a"])
    vb2 = r.stored("b")  # put again: neither prepared nor indexed
    r.indexed("b", vb2)
    assert r.snapshot() == (False, ["a"], ["a", "b"])
    r.prepared("b", vb2)
    assert r.snapshot() == (True, ["a", "b"], ["a", "b"])
    # without a search worker preparation alone makes a map ready
    plain = Readiness(indexing=False)
    plain.prepared("m", plain.stored("m"))
    assert plain.snapshot() == (True, ["m"], None)


def test_warm_up_and_map_preparation_run_the_methods(caplog: pytest.LogCaptureFixture) -> None:
    """The warm-up localises synthetic scans with every method without failing (a failure is
    logged, never raised); a map's preparation finds a free pose inside it and localises
    there."""
    with caplog.at_level(logging.ERROR, logger="shapeloc.service.worker"):
        assert warm_up_worker() > 0.0
    md = MapData.from_lists("room", "metric", ROOM)
    p = free_pose(md)
    assert p is not None and 0.0 < p[0] < 6.0 and 0.0 < p[1] < 4.0
    with caplog.at_level(logging.ERROR, logger="shapeloc.service.worker"):
        assert prepare_map(md) >= 0.0
    assert not caplog.records
    assert free_pose(MapData.from_lists("line", "metric", [[[0.0, 0.0], [1.0, 0.0]]])) is None


def test_a_workers_robots_share_their_maps_model() -> None:
    """Every robot on a map uses the model the worker built when the map was put (built once
    per map, not once per robot); a changed map put again gets a new one."""
    core = WorkerCore()
    core.handle(("map", MapData.from_lists("room", "metric", ROOM)))
    for rid in ("a", "b"):
        assert core.handle(("config", rid, "shape", "room", [1.0, 1.5, 0.2], None, None))[0] == "ok"
    models = {id(core.robots[r].localizer.tracker.model) for r in ("a", "b")}  # type: ignore[union-attr]
    assert models == {id(core.models["room"])}
    changed = [*ROOM, [[4.0, 3.0], [5.0, 3.0]]]
    core.handle(("map", MapData.from_lists("room", "metric", changed)))
    assert id(core.models["room"]) not in models


def test_a_moved_robot_travels_without_the_model_and_shares_its_new_workers() -> None:
    """A robot exported by one worker (the pickled bytes the service passes on) carries no
    map model; the importing worker's copy of the map gives it that worker's model."""
    a, b = WorkerCore(), WorkerCore()
    a.handle(("map", MapData.from_lists("room", "metric", ROOM)))
    b.handle(("map", MapData.from_lists("room", "metric", ROOM)))  # an equal copy
    assert a.handle(("config", "r", "shape", "room", [1.0, 1.5, 0.2], None, None))[0] == "ok"
    st, blob = a.handle(("export", "r"))
    assert st == "ok" and isinstance(blob, bytes)
    # the model stayed home: it pickles as its map, none of its grid in the robot's bytes
    model = a.models["room"]
    assert model.items.tobytes() not in blob and model.start.tobytes() not in blob
    assert b.handle(("import", "r", blob))[0] == "ok"
    assert b.robots["r"].localizer.tracker.model is b.models["room"]  # type: ignore[union-attr]
