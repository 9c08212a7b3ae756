"""The per-map view index of global localisation: candidate viewpoints (:mod:`.viewpoints`),
the index (:mod:`.index`), its build (:mod:`.build`) and where it is kept (:mod:`.cache`)."""

from service.core.reloc.view_index.build import build_index
from service.core.reloc.view_index.cache import IndexStore, clear_memory_cache, load_or_build_index
from service.core.reloc.view_index.index import ViewIndex
from service.core.reloc.view_index.viewpoints import candidate_viewpoints

__all__ = [
    "IndexStore",
    "ViewIndex",
    "build_index",
    "candidate_viewpoints",
    "clear_memory_cache",
    "load_or_build_index",
]
