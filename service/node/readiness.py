"""When the service is ready for robots, per map: what ``Health.ready``, ``maps_ready`` and
``maps_indexed`` report.

* A map is **indexed** once its view index of global localisation is built into the on-disk
  cache (by the search worker, right after the map is stored; loaded from that cache when
  the same map is stored again or the service restarts): a robot configured on it without an
  initial pose starts its global search at once. Only with a search worker (the default with
  worker processes); without one the first search builds it and ``maps_indexed`` is absent.
* A map is **ready** once every tracking worker holds it prepared
  (:func:`service.node.prepare.prepare_map`) and, with a search worker, its index is built
  (or its build failed: the first search then builds it): all of the map's first-use work is
  done, so robots configured on it are localised at full speed from their first scan and
  never share the cores with the index build (docs/decisions/0016: on a 2-core machine that
  build, 9 s of CPU for a 130-polyline building, raised a 20-robot fleet's p99 from 44-54 to
  75-87 ms, although the search worker runs at nice 19).
  A map put (or a restored map) is not ready until then; the service counts it in
  ``Health.maps`` (and ``get`` returns it) as soon as it is stored, and serves robots on it
  meanwhile.
* The **service** is ready once its tracking workers have warmed up
  (:func:`service.node.prepare.warm_up_worker`) and every stored map is ready.

Every put of a map starts a new version; a preparation or index that finishes for an older
version (the map was put again meanwhile) does not count. Thread-safe.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable
from concurrent.futures import Future
from typing import Any


class Readiness:
    """Per-map readiness and the workers' warm-up (see the module docstring)."""

    def __init__(self, indexing: bool) -> None:
        #: whether the service builds view indexes ahead (a search worker exists)
        self.indexing = indexing
        self._lock = threading.Lock()
        self._version: dict[str, int] = {}
        self._prepared: set[str] = set()
        self._indexed: set[str] = set()
        #: maps whose index build is over, built or failed (their readiness no longer waits)
        self._index_done: set[str] = set()
        self._warm: list[Future[Any]] = []
        self._next = 0

    def stored(self, map_id: str) -> int:
        """A new version of ``map_id`` is stored (neither ready nor indexed); returns it."""
        with self._lock:
            self._next += 1
            self._version[map_id] = self._next
            self._prepared.discard(map_id)
            self._indexed.discard(map_id)
            self._index_done.discard(map_id)
            return self._next

    def deleted(self, map_id: str) -> None:
        """``map_id`` was deleted."""
        with self._lock:
            self._version.pop(map_id, None)
            self._prepared.discard(map_id)
            self._indexed.discard(map_id)
            self._index_done.discard(map_id)

    def prepared(self, map_id: str, version: int) -> None:
        """Every tracking worker holds version ``version`` of ``map_id`` prepared."""
        with self._lock:
            if self._version.get(map_id) == version:
                self._prepared.add(map_id)

    def indexed(self, map_id: str, version: int, built: bool = True) -> None:
        """The index build of version ``version`` of ``map_id`` is over: built, or failed
        (``built`` false: the map is ready without it, the first search builds it)."""
        with self._lock:
            if self._version.get(map_id) == version:
                self._index_done.add(map_id)
                if built:
                    self._indexed.add(map_id)

    def warming(self, futures: Iterable[Future[Any]]) -> None:
        """The tracking workers' first replies (done once each has warmed up)."""
        with self._lock:
            self._warm = list(futures)

    def snapshot(self) -> tuple[bool, list[str], list[str] | None]:
        """``(service ready, ready map ids, indexed map ids or None)``, ids sorted."""
        with self._lock:
            warm = all(f.done() for f in self._warm)
            done = self._prepared & self._index_done if self.indexing else self._prepared
            ready = sorted(done)
            indexed = sorted(self._indexed) if self.indexing else None
            every = set(self._version) <= done
        return warm and every, ready, indexed
