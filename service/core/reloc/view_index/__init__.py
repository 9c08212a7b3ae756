"""The per-map view index of global localisation: candidate viewpoints (:mod:`.viewpoints`),
the index (:mod:`.index`), its build (:mod:`.build`) and its cache (:mod:`.cache`)."""

from service.core.reloc.view_index.build import build_index, index_key
from service.core.reloc.view_index.cache import (
    cache_path,
    clear_memory_cache,
    load_index,
    load_or_build_index,
    save_index,
)
from service.core.reloc.view_index.index import FORMAT_VERSION, ViewIndex
from service.core.reloc.view_index.viewpoints import candidate_viewpoints

__all__ = [
    "FORMAT_VERSION",
    "ViewIndex",
    "build_index",
    "cache_path",
    "candidate_viewpoints",
    "clear_memory_cache",
    "index_key",
    "load_index",
    "load_or_build_index",
    "save_index",
]
