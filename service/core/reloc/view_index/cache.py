"""The view index of each map, shared by the robots on it: the last few indexes in this
process' memory, else one an :class:`IndexStore` kept (the service's are files, read and
written at the edge: :mod:`service.adapters.maps.index_files`), else built.
"""

from __future__ import annotations

import logging
import threading
from collections import OrderedDict
from typing import Protocol

from service.core.reloc.config import GlobalConfig
from service.core.reloc.view_index.build import build_index, index_key
from service.core.reloc.view_index.index import ViewIndex
from service.core.sensor.scoring import sensor_model
from service.core.tracking.localizer import ShapeConfig
from service.core.types import MapData

log = logging.getLogger("shapeloc.global")


class IndexStore(Protocol):
    """Where view indexes are kept between runs, by map id and :func:`.build.index_key`."""

    def load(self, map_id: str, key: str) -> ViewIndex | None:
        """The index of that map and key, ``None`` if none is kept or it is not usable."""
        ...

    def save(self, index: ViewIndex) -> None:
        """Keep ``index`` (replacing the map's older ones); failures are the store's to report."""
        ...


_MEMO: OrderedDict[str, ViewIndex] = OrderedDict()
_MEMO_LOCK = threading.Lock()
_MEMO_SIZE = 4


def load_or_build_index(
    map_data: MapData,
    config: ShapeConfig | None = None,
    gconfig: GlobalConfig | None = None,
    store: IndexStore | None = None,
) -> ViewIndex:
    """The map's index: from this process' memory, else from ``store``, else built (and
    given to ``store``)."""
    config = config or ShapeConfig.for_kind(map_data.kind)
    gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
    key = index_key(map_data, config, gconfig)
    with _MEMO_LOCK:
        idx = _MEMO.get(key)
        if idx is not None:
            _MEMO.move_to_end(key)
            return idx
    idx = None if store is None else store.load(map_data.map_id, key)
    if idx is None:
        idx = build_index(map_data, config, gconfig)
        log.info(
            "view index of map %s built: %d viewpoints, %d units, %.1f s",
            map_data.map_id,
            len(idx.viewpoints),
            len(idx),
            idx.build_seconds,
        )
        if store is not None:
            store.save(idx)
    idx.sensor = sensor_model(map_data)
    with _MEMO_LOCK:
        _MEMO[key] = idx
        while len(_MEMO) > _MEMO_SIZE:
            _MEMO.popitem(last=False)
    return idx


def clear_memory_cache() -> None:
    """Forget the indexes held in this process (tests, benchmarks)."""
    with _MEMO_LOCK:
        _MEMO.clear()
