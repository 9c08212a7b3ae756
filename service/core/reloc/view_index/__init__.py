"""The per-map view index of global localisation: candidate viewpoints (:mod:`.viewpoints`),
the index (:mod:`.index`), its build (:mod:`.build`) and its cache (:mod:`.cache`)."""

from service.core.reloc.view_index.build import build_index
from service.core.reloc.view_index.cache import (
    clear_memory_cache,
    load_index,
    load_or_build_index,
    save_index,
)
from service.core.reloc.view_index.index import ViewIndex
from service.core.reloc.view_index.viewpoints import candidate_viewpoints

__all__ = [
    "ViewIndex",
    "build_index",
    "candidate_viewpoints",
    "clear_memory_cache",
    "load_index",
    "load_or_build_index",
    "save_index",
]
