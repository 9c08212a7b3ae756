"""The view index cache: on disk per map, and the last few indexes in this process' memory.
A file is named by the map id and its :func:`index_key`, written atomically and checked field
by field when read back: a corrupt or stale file is rebuilt, never trusted.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
import threading
from collections import OrderedDict
from pathlib import Path

import numpy as np

from service.core.reloc.config import GlobalConfig
from service.core.reloc.view_index.build import build_index, index_key
from service.core.reloc.view_index.index import ViewIndex
from service.core.sensor.scoring import sensor_model
from service.core.tracking.localizer import ShapeConfig
from service.core.types import MapData
from service.errors import LocalizationError

log = logging.getLogger("shapeloc.global")


def cache_path(cache_dir: Path, map_id: str, key: str) -> Path:
    """File of a map's index: ``<cache_dir>/viewindex-<safe map id>-<key[:20]>.npz``."""
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", map_id)[:80]
    return Path(cache_dir) / f"viewindex-{safe}-{key[:20]}.npz"


def save_index(index: ViewIndex, cache_dir: Path) -> Path:
    """Write ``index`` atomically and remove older files of its map id; return the path."""
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    path = cache_path(cache_dir, index.map_id, index.key)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=cache_dir)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **index.to_arrays())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    stem = cache_path(cache_dir, index.map_id, "").name[: -len(".npz")]
    stale = re.compile(re.escape(stem) + r"[0-9a-f]{20}\.npz")
    for old in cache_dir.glob(f"{stem}*.npz"):
        if old != path and stale.fullmatch(old.name):
            with contextlib.suppress(OSError):
                old.unlink()
    return path


def load_index(path: Path, key: str) -> ViewIndex:
    """Read an index file, checking its key and content; raises :class:`LocalizationError`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as exc:
        raise LocalizationError(f"unreadable index {path}: {exc}") from exc
    return ViewIndex.from_arrays(arrays, key)


_MEMO: OrderedDict[str, ViewIndex] = OrderedDict()
_MEMO_LOCK = threading.Lock()
_MEMO_SIZE = 4


def load_or_build_index(
    map_data: MapData,
    config: ShapeConfig | None = None,
    gconfig: GlobalConfig | None = None,
    cache_dir: Path | None = None,
) -> ViewIndex:
    """The map's index, shared by the robots on it: from this process' memory, else from a
    valid file in ``cache_dir``, else built (and saved there)."""
    config = config or ShapeConfig.for_kind(map_data.kind)
    gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
    key = index_key(map_data, config, gconfig)
    with _MEMO_LOCK:
        idx = _MEMO.get(key)
        if idx is not None:
            _MEMO.move_to_end(key)
            return idx
    idx = None
    if cache_dir is not None:
        path = cache_path(Path(cache_dir), map_data.map_id, key)
        if path.exists():
            try:
                idx = load_index(path, key)
                log.info("view index of map %s loaded from %s", map_data.map_id, path)
            except LocalizationError as exc:
                log.warning("view index %s not usable (%s); rebuilding", path, exc)
    if idx is None:
        idx = build_index(map_data, config, gconfig)
        log.info(
            "view index of map %s built: %d viewpoints, %d units, %.1f s",
            map_data.map_id,
            len(idx.viewpoints),
            len(idx),
            idx.build_seconds,
        )
        if cache_dir is not None:
            try:
                save_index(idx, Path(cache_dir))
            except OSError as exc:
                log.warning("view index of map %s not saved: %s", map_data.map_id, exc)
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
