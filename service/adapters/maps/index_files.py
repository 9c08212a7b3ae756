"""View index files: a map's view index of global localisation kept on disk between runs (its
build takes seconds to minutes on a building). One file per map id, named by the index's key,
written atomically and checked field by field when read back: a corrupt or stale file is
rebuilt, never trusted. The core asks for an index through
:class:`service.core.reloc.view_index.IndexStore`; :class:`IndexFiles` is the service's.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from service.errors import LocalizationError

if TYPE_CHECKING:  # the service process holds the store, its workers the indexes
    from service.core.reloc.view_index import ViewIndex

log = logging.getLogger("shapeloc.global")


def index_path(directory: Path, map_id: str, key: str) -> Path:
    """File of a map's index: ``<directory>/viewindex-<safe map id>-<key[:20]>.npz``."""
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", map_id)[:80]
    return Path(directory) / f"viewindex-{safe}-{key[:20]}.npz"


def save_index(index: ViewIndex, directory: Path) -> Path:
    """Write ``index`` atomically and remove older files of its map id; return the path."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    path = index_path(directory, index.map_id, index.key)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=directory)
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
    stem = index_path(directory, index.map_id, "").name[: -len(".npz")]
    stale = re.compile(re.escape(stem) + r"[0-9a-f]{20}\.npz")
    for old in directory.glob(f"{stem}*.npz"):
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
    from service.core.reloc.view_index import ViewIndex

    return ViewIndex.from_arrays(arrays, key)


@dataclass(frozen=True)
class IndexFiles:
    """The view indexes kept in ``directory`` (an :class:`~service.core.reloc.view_index.
    IndexStore`). A file that cannot be read is reported and rebuilt; one that cannot be
    written is reported and the index is used from memory."""

    directory: Path

    def load(self, map_id: str, key: str) -> ViewIndex | None:
        path = index_path(self.directory, map_id, key)
        if not path.exists():
            return None
        try:
            idx = load_index(path, key)
        except LocalizationError as exc:
            log.warning("view index %s not usable (%s); rebuilding", path, exc)
            return None
        log.info("view index of map %s loaded from %s", map_id, path)
        return idx

    def save(self, index: ViewIndex) -> None:
        try:
            save_index(index, self.directory)
        except OSError as exc:
            log.warning("view index of map %s not saved: %s", index.map_id, exc)
